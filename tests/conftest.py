"""Shared fixtures: small fixture worlds generated once per test session."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest

from harness.fixture import FixtureSpec, generate

ROOT = Path(__file__).resolve().parents[1]


def no_figures(cfg: Any) -> Any:
    """``cfg`` without the figures and the page: for a test that reads neither (they cost about
    8 s a run on the fixture; no cache key holds ``[report]``, so nothing else changes)."""
    return dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, plots=False, html=False))


#: A small world written in every log format, for ingester comparisons.
SMALL = FixtureSpec(frames=12, width=48, height=64, objects=2, loop_scale=1.0)


@pytest.fixture(scope="session")
def small_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate(tmp_path_factory.mktemp("small") / "fx", SMALL, all_formats=True)


@pytest.fixture(scope="session")
def default_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The default fixture (what `make reproduce-table` uses)."""
    return generate(tmp_path_factory.mktemp("default") / "fx", FixtureSpec())


@pytest.fixture(scope="session")
def local_run(tmp_path_factory: pytest.TempPathFactory, default_world: Path) -> tuple:
    """The whole pipeline on the default fixture with the local executor.

    (pipeline, record, out).
    """
    from harness.config.load import load_config
    from harness.pipeline.chain import Pipeline

    out = tmp_path_factory.mktemp("run")
    cfg = load_config(ROOT / "datasets" / "fixture.toml", data_root=str(default_world))
    p = Pipeline(cfg, out)
    return p, p.run(), out


def one_error(capsys: pytest.CaptureFixture) -> str:
    """What a command printed on stderr, checked to be one ``ERROR:`` line and no traceback."""
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    return err

"""The command layer: exit codes and messages."""

from __future__ import annotations

from pathlib import Path

import pytest

from harness.cli import main
from harness.config.assemble import load_config
from harness.errors import ConfigError

from ..conftest import ROOT


def test_bad_input_is_one_error_line_and_exit_1(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    p = tmp_path / "x.txt"
    p.write_text("nope")
    assert main(["ingest", str(p), "--session", "s", "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") and "unknown log format" in err and "Traceback" not in err


def test_fixture_and_ingest_commands(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert (
        main(
            [
                "fixture",
                "--out",
                str(tmp_path / "fx"),
                "--frames",
                "6",
                "--width",
                "32",
                "--height",
                "40",
                "--loop-scale",
                "1.0",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "ingest",
                str(tmp_path / "fx" / "mcap" / "2012-11-17.mcap"),
                "--session",
                "2012-11-17",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 0
    )
    assert "6 frames" in capsys.readouterr().out
    assert (
        main(
            [
                "fixture",
                "--out",
                str(tmp_path / "fx2"),
                "--frames",
                "4",
                "--width",
                "32",
                "--height",
                "40",
                "--formats",
                "mcap",
            ]
        )
        == 0
    )
    assert sorted(p.name for p in (tmp_path / "fx2" / "mcap").iterdir()) == [
        "2012-01-22.mcap",
        "2012-03-31.mcap",
        "2012-08-04.mcap",
        "2012-11-17.mcap",
    ]
    capsys.readouterr()
    assert main(["fixture", "--out", str(tmp_path / "fx3"), "--formats", "ros2,tiff"]) == 1
    err = capsys.readouterr().err
    assert (
        err.startswith("ERROR: harness fixture: formats must name one of")
        and not (tmp_path / "fx3").exists()
    )
    assert main(["fixture", "--out", str(tmp_path / "fx4"), "--render-scale", "0"]) == 1
    assert "--render-scale = 0 is out of range; allowed: >= 1" in capsys.readouterr().err


def test_config_rejects_unknown_keys(tmp_path: Path) -> None:
    text = (
        (ROOT / "datasets" / "fixture.toml")
        .read_text()
        .replace("[pairs]\n", "[pairs]\nmax_yaw_dif_deg = 30\n")
    )
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['max_yaw_dif_deg'\]"):
        load_config(p)


def test_nclt_config_loads(tmp_path: Path) -> None:
    cfg = load_config(ROOT / "datasets" / "nclt.toml", data_root=str(tmp_path))
    assert [s.name for s in cfg.sessions] == [
        "2012-01-22",
        "2012-03-31",
        "2012-08-04",
        "2012-11-17",
    ]
    assert cfg.descriptor.input_size == 256


def test_stage_commands_on_the_fixture(
    default_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    args = [
        "--config",
        str(ROOT / "datasets" / "fixture.toml"),
        "--data-root",
        str(default_world),
        "--out",
        str(tmp_path),
    ]
    assert main(["pairs", *args]) == 0
    out = capsys.readouterr().out
    assert "pairs ->" in out and '"pairs_per_season_pair"' in out
    assert main(["proposals", *args]) == 0
    assert "edges" in capsys.readouterr().out


def test_fixture_section_chooses_formats_and_render_scale(tmp_path: Path) -> None:
    """A config with [fixture] render_scale and one format generates and ingests."""
    import dataclasses

    from harness.config.assemble import load_config
    from harness.fixture.config import FixtureConfig
    from harness.pipeline.chain import Pipeline
    from harness.pipeline.preflight import generate_fixture
    from harness.pipeline.stages import frame_table, ingest_logs

    cfg = load_config(ROOT / "datasets" / "fixture.toml", data_root=str(tmp_path / "world"))
    fx = FixtureConfig(
        generate=True, frames=6, width=64, height=80, render_scale=2, formats=("ros2",)
    )
    sessions = tuple(
        dataclasses.replace(s, source=str(tmp_path / "world" / "ros2" / s.name))
        for s in cfg.sessions
    )
    cfg = dataclasses.replace(cfg, fixture=fx, sessions=sessions, annotations=tmp_path / "ann.csv")
    p = Pipeline(cfg, tmp_path / "out")
    generate_fixture(p)
    frames = frame_table(p, ingest_logs(p)).df
    assert len(frames) == 24 and set(frames["width"]) == {64} and set(frames["height"]) == {80}
    assert all(str(u).endswith(".jpg") for u in frames["image"])

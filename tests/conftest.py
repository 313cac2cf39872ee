"""Shared fixtures: small fixture worlds generated once per test session."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from harness.fixture import FixtureSpec, generate

ROOT = Path(__file__).resolve().parents[1]


def no_figures(cfg: Any) -> Any:
    """``cfg`` without the figures and the page: for a test that reads neither (they cost about
    8 s a run on the fixture; no cache key holds ``[report]``, so nothing else changes)."""
    return dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, plots=False, html=False))


#: The no-change null's pairs in a test that does not read the null's own figures: its documented
#: 100 pairs are checked through to ``alarms.csv`` and the page by the end-to-end tests of
#: ``tests/detect`` (the fixture's and the real revisits'); 20 pairs cost a fifth of the scoring.
TEST_NULL_PAIRS = 20


def small_null_config(config: Path, tmp: Path) -> Path:
    """``config`` (a TOML file without a ``[detect.null]`` table) with :data:`TEST_NULL_PAIRS`
    null pairs, written into ``tmp``; its relative paths read from the repository's root."""
    text = config.read_text()
    for rel in ('"datasets/', '"annotations/'):
        text = text.replace(rel, f'"{ROOT}/{rel[1:]}')
    out = tmp / f"{config.stem}-null{TEST_NULL_PAIRS}.toml"
    out.write_text(f"{text.rstrip()}\n\n[detect.null]\npairs = {TEST_NULL_PAIRS}\n")
    return out


def blob_wall(seed: int, width: int, height: int) -> Any:
    """A wall ``width`` x ``height`` of coloured blobs on grey, for a camera to slide along: a
    folder test's frames are its windows (regions and keypoints everywhere)."""
    import cv2  # here, not at the top: numpy and OpenCV load after the harness pins their kernels
    import numpy as np

    rng = np.random.default_rng(seed)
    wall = np.full((height, width, 3), 120, np.uint8)
    for _ in range(width * height // 300):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        cv2.circle(wall, (int(rng.integers(0, width)), int(rng.integers(0, height))),
                   int(rng.integers(2, 12)), c, -1)  # fmt: skip
    return wall


#: A small world written in every log format, for ingester comparisons.
SMALL = FixtureSpec(frames=12, width=48, height=64, objects=2, loop_scale=1.0)


@pytest.fixture(scope="session")
def small_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate(tmp_path_factory.mktemp("small") / "fx", SMALL, all_formats=True)


@pytest.fixture(scope="session")
def default_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The default fixture (what `make reproduce-table` uses), one for every worker: the stage
    keys of a run hold where its logs are, so workers share runs only on the same world."""
    shared = _shared_dir(tmp_path_factory)
    world = shared / "default-world" / "fx"
    with _locked(shared / "default-world.lock"):
        if not (world / "fixture.json").exists():
            generate(world, FixtureSpec())
    return world


@pytest.fixture(scope="session")
def local_run(tmp_path_factory: pytest.TempPathFactory, default_world: Path) -> tuple:
    """The whole pipeline on the default fixture with the local executor.

    (pipeline, record, out).
    """
    from harness.config.assemble import load_config
    from harness.pipeline.chain import Pipeline

    out = tmp_path_factory.mktemp("run")
    cfg = load_config(ROOT / "datasets" / "fixture.toml", data_root=str(default_world))
    with shared_stages(tmp_path_factory, "fixture-run", out):
        p = Pipeline(cfg, out)
        rec = p.run()
    return p, rec, out


def one_error(capsys: pytest.CaptureFixture) -> str:
    """What a command printed on stderr, checked to be one ``ERROR:`` line and no traceback."""
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    return err


def seed_cache(run: Path, out: Path, stages: tuple[str, ...] | None = None) -> Path:
    """Copy a finished run's stage cache (every stage, or ``stages``) into a new ``out``.

    Entries are keyed by their inputs, config and code, so a test's run into ``out`` reuses what
    the suite already computed and recomputes only what its own config changes: no test trains a
    model another already trained (issue 50). Copies, not links: a test may damage its entries.
    """
    from harness.runtime.outdirs import MARKER

    out.mkdir(parents=True, exist_ok=True)
    for d in sorted((run / "cache").iterdir()):
        if d.is_dir() and (stages is None or d.name in stages):
            shutil.copytree(d, out / "cache" / d.name, dirs_exist_ok=True)
    shutil.copy(run / MARKER, out / MARKER)
    return out


def _shared_dir(factory: pytest.TempPathFactory) -> Path:
    """A folder every worker of this test session sees: under pytest-xdist (``make test`` runs
    two) the parent of the workers' base folders, else the session's own base folder."""
    base = factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextlib.contextmanager
def shared_stages(factory: pytest.TempPathFactory, name: str, out: Path) -> Iterator[None]:
    """Run the block (a pipeline into ``out``) once per test session, whatever the workers.

    Under a lock named ``name``: where another worker already ran it, ``out`` is first seeded
    with that run's stage cache (:func:`seed_cache`), so the block recomputes only what is not
    cached (its reports); after the block, every entry it computed that is not yet published is
    published for the others (a block that runs more of the stages, such as the no-change null,
    leaves them to the next). Entries are content-keyed: a seeded entry is exactly what the block
    would have computed.
    """
    shared = _shared_dir(factory)
    done = shared / f"{name}.stages"
    with _locked(shared / f"{name}.lock"):
        if done.is_dir():
            seed_cache(done, out)
        yield
        if not done.is_dir():
            tmp = shared / f".{name}.{os.getpid()}.tmp"
            seed_cache(out, tmp)
            tmp.rename(done)
            return
        for entry in sorted((out / "cache").glob("*/*")):
            dst = done / "cache" / entry.parent.name / entry.name
            if entry.is_dir() and not entry.name.startswith(".") and not dst.exists():
                dst.parent.mkdir(parents=True, exist_ok=True)
                tmp = dst.parent / f".{entry.name}.{os.getpid()}.tmp"
                shutil.copytree(entry, tmp)
                tmp.rename(dst)


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path`` (created) across the workers, held for the block."""
    with open(path, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


#: The file that computes the shared fixture run (:func:`local_run`) first: ``make test`` hands
#: it to one worker while the other runs the files that need no fixture run (issue 50: that
#: worker waited 48 s on the run's lock before). Then the rest, those measured longest first (the
#: seconds ``pytest --durations=0`` measured under ``make test`` on this project's machine), so that
#: the two workers end together; files not listed run last, in collection order.
FIRST = "tests/detect/test_detect.py"
LONGEST_FIRST = (
    "tests/localizers/test_localizers.py",  # 120 s
    "tests/pipeline/test_pipeline.py",  # 71
    "tests/localizers/test_byo_localizer.py",  # 69
    "tests/kernels/test_kernels.py",  # 65
    "tests/runtime/test_ray.py",  # 60 (after test_detect: it shares the detect run)
    "tests/test_recipes.py",  # 37
    "tests/pairs/test_no_poses.py",  # 35
    "tests/localizers/test_keypoints.py",  # 31
    "tests/retrieval/test_db_stride.py",  # 28
    "tests/pipeline/test_safety_outputs.py",  # 18
    "tests/runtime/test_safety_cache.py",  # 16
    "tests/fixture/test_fixture.py",  # 14
    "tests/test_recipe_files.py",  # 12
    "tests/descriptors/test_projection.py",  # 12
    "tests/evaluate/test_evidence.py",  # 12
    "tests/runtime/test_gc.py",  # 11
    "tests/cli/test_readme_paths.py",  # 7
)
#: The fixtures that need the shared fixture run (or its world).
SHARED_RUNS = {"local_run", "default_world"}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the test files for two workers (``--dist loadfile --no-loadscope-reorder``): see
    :data:`FIRST`. Tests keep their order inside a file."""
    files: dict[str, list[pytest.Item]] = {}
    for item in items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)

    def rank(f: str) -> tuple[int, int]:
        if f == FIRST:
            return 0, 0
        if not any(SHARED_RUNS & set(getattr(i, "fixturenames", ())) for i in files[f]):
            return 1, 0
        if f in LONGEST_FIRST:
            return 2, LONGEST_FIRST.index(f)
        return 3, 0

    order = sorted(files, key=rank)  # stable: collection order within a rank
    items[:] = [i for f in order for i in files[f]]

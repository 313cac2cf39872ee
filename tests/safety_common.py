"""Helpers of the safety tests (tests/*/test_safety_*.py): a config, a small log."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.fixture import writers as W
from harness.records import Pose

from .conftest import ROOT, one_error

FIXTURE_TOML = ROOT / "datasets" / "fixture.toml"
TINY = ["--frames", "6", "--width", "32", "--height", "40", "--loop-scale", "1.0"]


_err = one_error


def _config(tmp: Path, text_edit: tuple[str, str] | None = None, extra: str = "") -> Path:
    text = FIXTURE_TOML.read_text()
    if text_edit:
        assert text_edit[0] in text
        text = text.replace(*text_edit)
    p = tmp / "c.toml"
    p.write_text(text + extra)
    return p


def _log(tmp: Path, fmt: str, poses: list[Pose] | None = None, n: int = 6, **kw: object) -> Path:
    rgb = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(n)]
    poses = poses or [
        Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(2 * n)
    ]
    if fmt == "mcap":
        path = tmp / "log.mcap"
        W.write_mcap(path, frames, poses, **kw)  # type: ignore[arg-type]
    elif fmt == "ros1":
        path = tmp / "log.bag"
        W.write_ros1(path, frames, poses)
    else:
        path = tmp / "bag"
        W.write_ros2(path, frames, poses, storage="sqlite3", **kw)  # type: ignore[arg-type]
    return path

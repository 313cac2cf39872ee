"""Frames that carry no place (docs/method.md, *Frames that carry no place*).

Measured on frames made here (black, grey, a frame at 5% of its brightness, a real frame) and on
the real train ride of ``../shared/realdata/nordland-dev`` with dark, blank, stopped and tunnel
stretches spliced into its map (``python -m bench.pairing_truth``'s case, made the same way).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.cli import main
from harness.pairs.config import PairsConfig
from harness.pairs.place import contrast

from ..conftest import ROOT

cv2 = pytest.importorskip("cv2")
NORDLAND = ROOT.parent / "shared" / "realdata" / "nordland-dev"


def test_the_default_threshold_parts_frames_with_no_place_from_real_frames() -> None:
    """The rule written before looking at the ride: half the lowest contrast of nordland-dev's 600
    real frames (22.3 grey levels), rounded down: 10. Black, grey and a frame at 5% of its
    brightness fall under it; every real frame of both seasons lies above it."""
    t = PairsConfig().min_place_contrast
    assert t == 10.0
    made = np.zeros((32, 64, 3), np.uint8)
    assert contrast(made) == 0.0 and contrast(made + 128) == 0.0
    rng = np.random.default_rng(0)
    scene = np.full((240, 320, 3), 120, np.uint8)  # a scene: blocks of many shades
    for _ in range(80):
        x, y = rng.integers(0, 300), rng.integers(0, 220)
        cv2.rectangle(scene, (int(x), int(y)), (int(x) + 30, int(y) + 20),
                      tuple(int(v) for v in rng.integers(0, 255, 3)), -1)  # fmt: skip
    assert contrast(scene) > 2 * t
    assert contrast((scene * 0.05).astype(np.uint8)) < t
    if (NORDLAND / "winter").is_dir():
        real = [
            contrast(cv2.imread(str(f)))
            for s in ("summer", "winter")
            for f in sorted((NORDLAND / s).glob("*.png"))
        ]
        assert len(real) == 600 and min(real) > 2 * t, min(real)


@pytest.mark.skipif(
    not (NORDLAND / "winter").is_dir(),
    reason=f"no real seasons here: {NORDLAND} is absent (shared/realdata is read, never committed)",
)
def test_dark_blank_and_stopped_map_frames_pair_as_well_as_without_them(
    tmp_path: Path,
) -> None:
    """The ride's map with 17 dark frames at its start, a black and a grey frame, a stop (one frame
    20 times) and 13 dark frames at its end: the 32 frames with no place are named and counted,
    none is any query frame's pair, and the queries pair as well as the plain ride does (80%
    within 2 frames, docs/folders.md; at most 2 points less)."""
    from bench.pairing_truth import spliced_nordland

    made = spliced_nordland(tmp_path / "ride", splice=True)
    assert made is not None
    mdir, qdir, place = made
    out = tmp_path / "out"
    argv = ["detect", "--map-images", str(mdir), "--query-images", str(qdir), "--calibration",
            "within-run", "--out", str(out)]  # fmt: skip
    said: list[str] = []
    hear = logging.Handler(logging.WARNING)  # on the logger itself: the CLI resets the root's
    hear.emit = lambda r: said.append(r.getMessage())  # type: ignore[method-assign]
    logging.getLogger("harness.pairs.place").addHandler(hear)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(argv) == 0
    finally:
        logging.getLogger("harness.pairs.place").removeHandler(hear)
    blank = sorted(k for k, v in place.items() if v is None)
    assert len(blank) == 32
    rec = json.loads((out / "detect.json").read_text())
    no_place = rec["pairing"]["no_place"]
    assert sorted(no_place["names"]) == blank and no_place["min_place_contrast"] == 10.0
    assert all(f["contrast"] < 10 for f in no_place["frames"])
    assert any("32 frames carry no place" in w and blank[0] in w for w in said), said
    fr = pd.read_csv(out / "frames.csv")
    assert len(fr) == 300 and not set(fr["r_name"]) & set(blank)
    got = np.array([place[str(r)] for r in fr["r_name"]], np.float64)
    truth = fr["name"].str.slice(1, 5).astype(int).to_numpy()
    share = float(np.mean(np.abs(got - truth) <= 2))
    assert share >= 0.78, share

"""Frames that carry no place (docs/decisions.md, *Frames that carry no place*).

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


#: The tests that read the real ride skip, saying why, where it is absent.
needs_the_ride = pytest.mark.skipif(
    not (NORDLAND / "winter").is_dir(),
    reason=f"no real seasons here: {NORDLAND} is absent (shared/realdata is read, never committed)",
)


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


@needs_the_ride
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


@needs_the_ride
def test_a_query_run_backwards_over_part_of_a_map_dark_where_it_is_not_pairs_in_order(
    tmp_path: Path,
) -> None:
    """The real ride's first 200 winter frames driven backwards (a query run the other way round,
    over part of the map), fogged at places 131-170 (blurred and hazed: little texture, their
    contrast kept), against the summer map whose first 17 frames are dark (the camera starting
    up where the query's frames show a lit station). The sequence's one path: the queries whose
    place is dark in the map are left unpaired and named; the others pair within 2 frames of
    their place, the fog from the path through it, and no map frame takes more than 5 of them
    (docs/decisions.md, *Pairs without poses*)."""
    import cv2

    rng = np.random.default_rng(3)
    mdir, qdir = tmp_path / "map", tmp_path / "query"
    mdir.mkdir()
    qdir.mkdir()
    for i, f in enumerate(sorted((NORDLAND / "summer").glob("*.png"))):
        img = cv2.imread(str(f))
        if i < 17:
            glow = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 6) * 0.15
            img = np.clip(2 + glow + rng.normal(0, 0.5, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(mdir / f"m{i:04d}.png"), img)
    winter = sorted((NORDLAND / "winter").glob("*.png"))[:200]
    for k, i in enumerate(range(199, -1, -1)):
        img = cv2.imread(str(winter[i]))
        if 131 <= i <= 170:
            haze = 0.75 * cv2.GaussianBlur(img.astype(np.float32), (0, 0), 2.5) + 0.25 * 200
            img = np.clip(haze + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(qdir / f"w{k:04d}.png"), img)
    out = tmp_path / "out"
    argv = ["detect", "--map-images", str(mdir), "--query-images", str(qdir), "--calibration",
            "within-run", "--out", str(out)]  # fmt: skip
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv) == 0
    rec = json.loads((out / "detect.json").read_text())
    unpaired = {f["name"] for f in rec["pairing"]["unpaired"]}
    dark_places = {f"w{199 - i:04d}.png" for i in range(17)}
    assert unpaired == dark_places, sorted(unpaired ^ dark_places)
    fr = pd.read_csv(out / "frames.csv")
    no_place = {n for n in rec["pairing"]["no_place"]["names"] if n.startswith("w")}
    assert len(no_place) <= 4, no_place  # the fog keeps its contrast: it carries a place
    # every other frame is in frames.csv, less any whose fogged image gave no candidate box
    assert not set(fr["name"]) & unpaired and len(fr) >= 200 - 17 - len(no_place) - 4
    got = fr["r_name"].str.slice(1, 5).astype(int).to_numpy()
    truth = 199 - fr["name"].str.slice(1, 5).astype(int).to_numpy()
    assert float(np.mean(np.abs(got - truth) <= 2)) >= 0.95
    assert fr["r_name"].value_counts().max() <= 5 and not rec["pairing"]["hubs"]

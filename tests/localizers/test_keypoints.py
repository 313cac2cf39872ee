"""Keypoint localization, Selective Search proposals and the detector's Table D rows.

A synthetic pair whose truth is known: a textured scene seen twice with a shift and a small
parallax, and a new textured object pasted into the second view only. The object's keypoints
find no match in the map frame, the background's do; the object's box must score a higher share
of keypoints that do not localize than every background box, the pair's geometry is a fitted
fundamental matrix. (The plain difference of the same pair: tests/detect/test_difference.py.)
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.localizers.config import KeypointConfig, check_keypoints
from harness.localizers.keypoints import localized, pair_shares, share_map
from harness.proposals.builtin import selective_boxes
from harness.proposals.config import SelectiveConfig

cv2 = pytest.importorskip("cv2")

W, H = 480, 360
OBJECT = (300, 120, 380, 200)  # the new object's box in the query frame


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Blobs, lines and noise: a scene with plenty of SIFT keypoints (uint8 gray)."""
    img = np.full((h, w), 120, np.uint8)
    for _ in range(260):
        c = tuple(int(v) for v in rng.integers(0, [w, h]))
        cv2.circle(img, c, int(rng.integers(3, 14)), int(rng.integers(0, 255)), -1)
    for _ in range(60):
        p, q = rng.integers(0, [w, h], 2), rng.integers(0, [w, h], 2)
        cv2.line(img, tuple(map(int, p)), tuple(map(int, q)), int(rng.integers(0, 255)), 2)
    return cv2.GaussianBlur(img, (3, 3), 0)


def _pair() -> tuple[np.ndarray, np.ndarray]:
    """(query, map) gray frames: the map's scene shifted by (7, 4) px, plus a new object."""
    rng = np.random.default_rng(5)
    scene = _texture(rng, H + 40, W + 40)
    m = scene[20 : 20 + H, 20 : 20 + W].copy()
    q = scene[24 : 24 + H, 27 : 27 + W].copy()
    x1, y1, x2, y2 = OBJECT
    q[y1:y2, x1:x2] = _texture(np.random.default_rng(99), y2 - y1, x2 - x1)
    return q, m


def _background_boxes() -> np.ndarray:
    return np.array([[40, 40, 120, 120], [150, 220, 230, 300], [60, 230, 140, 310],
                     [180, 40, 260, 120]], np.float64)  # fmt: skip


def test_a_new_objects_keypoints_do_not_localize_and_the_backgrounds_do() -> None:
    q, m = _pair()
    kc = KeypointConfig()
    xq, ok_q, _, _, geo = localized(q, m, kc)
    assert geo.model == "fundamental" and geo.inliers >= 30 and geo.matches >= geo.inliers
    x1, y1, x2, y2 = OBJECT
    inside = (xq[:, 0] >= x1) & (xq[:, 0] < x2) & (xq[:, 1] >= y1) & (xq[:, 1] < y2)
    assert inside.sum() >= 5
    assert ok_q[inside].mean() < 0.2 < 0.7 < ok_q[~inside].mean()
    boxes = np.vstack([np.array(OBJECT, np.float64), _background_boxes()])
    share, _ = pair_shares(q, m, boxes, kc)
    assert share[0] > 0.6 and (share[1:] < 0.35).all(), share
    assert share[0] > share[1:].max() + 0.3


def test_the_share_map_has_its_prior_and_sizes_are_shares_of_the_frame() -> None:
    kc = KeypointConfig()
    # one keypoint that does not localize: its peak is 1 / (1 + prior), never 1
    smap = share_map((100, 100), np.array([[50.0, 50.0]]), np.array([True]), kc)
    assert smap.max() == pytest.approx(1 / (1 + kc.prior), rel=0.02)
    # no keypoint at all: no change anywhere
    assert share_map((100, 100), np.zeros((0, 2)), np.zeros(0, bool), kc).max() == 0
    # the same scene at twice the size: the same share at the same place
    small = share_map(
        (100, 120), np.array([[30.0, 40.0], [60.0, 40.0]]), np.array([True, False]), kc
    )
    big = share_map(
        (200, 240), np.array([[60.0, 80.0], [120.0, 80.0]]), np.array([True, False]), kc
    )
    assert big[80, 60] == pytest.approx(small[40, 30], rel=0.05)


def test_without_enough_matches_no_geometry_is_claimed() -> None:
    rng = np.random.default_rng(1)
    a, b = _texture(rng, 120, 160), _texture(np.random.default_rng(2), 120, 160)
    *_, geo = localized(a, b, KeypointConfig(min_matches=500))
    assert geo.model == "none" and geo.inliers == 0


@pytest.mark.parametrize(
    ("key", "value", "words"),
    [
        ("features", "surf", "sift, orb, akaze"),
        ("geometry", "affine", "fundamental or homography"),
        ("sigma", 0.0, "(0, 0.5)"),
        ("min_matches", 4, ">= 8"),
    ],
)
def test_a_bad_keypoints_option_is_named(key: str, value: object, words: str) -> None:
    import dataclasses

    from harness.errors import ConfigError

    want = rf"\[detect.keypoints\]: {key} = .* is out of range; allowed: {re.escape(words)}"
    with pytest.raises(ConfigError, match=want):
        check_keypoints(dataclasses.replace(KeypointConfig(), **{key: value}), "[detect.keypoints]")


def test_selective_search_meets_the_new_object_within_its_limits() -> None:
    q, _ = _pair()
    rgb = cv2.cvtColor(q, cv2.COLOR_GRAY2RGB)
    cfg = SelectiveConfig(max_boxes=300)
    boxes, score = selective_boxes(rgb, cfg)
    assert 0 < len(boxes) <= 300 and (np.diff(score) <= 0).all()  # Selective Search's order
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]) / (W * H)
    assert (area >= cfg.min_area_frac * 0.9).all() and (area <= cfg.max_area_frac * 1.1).all()
    again, _ = selective_boxes(rgb, cfg)
    np.testing.assert_array_equal(boxes, again)  # one thread: the same boxes every time


# ---------------------------------------------------------------- as a localizer and a detector


def test_keypoints_is_a_localizer_with_its_table_l_row(local_run: tuple, tmp_path: Path) -> None:
    """``[[localizers]] keypoints = {}`` beside the autoencoder: its own Table L row, ranks with
    ``r`` in (0, 1] and ``L`` = ``levels``, and its pairs' geometry counted."""
    from harness.cli import main

    from ..conftest import ROOT, seed_cache

    p, _, run = local_run
    text = (ROOT / "datasets" / "fixture.toml").read_text()
    text = text.replace('"annotations/', f'"{ROOT}/annotations/')
    text = text.replace('"datasets/models"', f'"{ROOT}/datasets/models"')
    text = text.replace("[report]\n", "[report]\nplots = false\nhtml = false\n")
    text += (
        '\n[[localizers]]\nname = "autoencoder"\ndescriptor = { name = "autoencoder", '
        'input_size = 64, input_norm = "per_crop", epochs = 6, batch_size = 32, '
        'max_train_subimages = 3000, train_samples = 6000, trained_models = "'
        f'{ROOT}/datasets/models" }}\n\n[[localizers]]\nname = "kp"\nkeypoints = {{}}\n'
    )
    cfg = tmp_path / "kp.toml"
    cfg.write_text(text)
    out = seed_cache(run, tmp_path / "out")
    assert main(["reproduce", "--config", str(cfg), "--data-root", str(p.cfg.data_root),
                 "--out", str(out)]) == 0  # fmt: skip
    t = pd.read_csv(out / "tableL.csv")
    assert t["localizer"].tolist() == ["autoencoder", "kp", "all localizers"]
    ranks = pd.read_parquet(out / "ranks.parquet")
    kp = ranks[ranks["localizer"] == "kp"]
    assert len(kp) and (kp["L"] == 1000).all() and kp["r"].between(1e-3, 1).all()
    assert (kp["place_size"] == 1).all()  # the place is the paired frame itself
    rec = json.loads((out / "run.json").read_text())
    assert "keypoint localization" in json.dumps(rec) or "keypoints" in json.dumps(rec)


def test_detect_with_keypoints_writes_each_pairs_geometry_and_the_difference_row(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``harness detect --localizer keypoints`` as typed on the fixture: ``alignment.csv`` holds
    each pair's model, inliers and image names; Table D carries the plain-difference rows, and
    the detector's verdict is measured against it too."""
    from harness.cli import main

    from ..conftest import ROOT, small_null_config

    p, _, _ = local_run
    out = tmp_path / "d"
    cfg = small_null_config(ROOT / "datasets" / "fixture.toml", tmp_path)  # its null is not read
    argv = ["detect", "--config", str(cfg), "--data-root",
            str(p.cfg.data_root), "--map", "2012-01-22", "--query", "2012-03-31",
            "--localizer", "keypoints", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    al = pd.read_csv(out / "alignment.csv")
    assert set(al["align"]) <= {"fundamental", "none"} and (al["align"] == "fundamental").any()
    assert {"q_image", "r_image", "inliers"} <= set(al.columns)
    assert al["q_image"].str.endswith((".tiff", ".jpg", ".png")).all()
    t = pd.read_csv(out / "tableD.csv")
    assert "plain difference on the detector's boxes (pixels, no localizer)" in set(t["row"])
    det = t[t["row"] == "detector"].iloc[0]
    assert det["best_no_pixel"] in (
        "size_prior",
        "cover_count",
        "plain_difference",
        "difference_same_boxes",
    )
    rec = json.loads((out / "detect.json").read_text())
    assert rec["options"]["localizer"] == "keypoints" and "keypoints" in rec["options"]
    assert "plain difference, registered" in (out / "tableD.md").read_text()


def test_a_map_frames_keypoints_are_detected_once_for_every_query_that_pairs_with_it(
    tmp_path: Path,
) -> None:
    """Three query frames paired with one map frame: every frame's keypoints are detected once
    (the map's for all three pairs), and each pair's shares are those of the pair computed alone;
    a frame in a further pair (the null's query against another copy) is not detected again."""
    from harness.localizers.keypoints import MapFeatures, pair_keypoint_ranks

    q, m = _pair()
    paths = {}
    for name, img in (("q0", q), ("q1", np.roll(q, 3, axis=1)), ("q2", np.roll(q, 5, axis=0)),
                      ("m", m)):  # fmt: skip
        paths[name] = str(tmp_path / f"{name}.png")
        cv2.imwrite(paths[name], img)
    kc = KeypointConfig()
    boxes = np.vstack([np.array(OBJECT, np.float64), _background_boxes()])
    maps = MapFeatures(kc)
    for name in ("q0", "q1", "q2"):
        geo, got = pair_keypoint_ranks(paths[name], paths["m"], (W, H), boxes, kc, maps)
        alone = pair_keypoint_ranks(paths[name], paths["m"], (W, H), boxes, kc)
        np.testing.assert_array_equal(got, alone[1])
        assert geo == alone[0]
    assert maps.detected == 4  # three query frames and the map frame, once each
    geo, got = pair_keypoint_ranks(paths["q0"], paths["q1"], (W, H), boxes, kc, maps)
    np.testing.assert_array_equal(got, pair_keypoint_ranks(paths["q0"], paths["q1"], (W, H),
                                                           boxes, kc)[1])  # fmt: skip
    assert maps.detected == 4  # q0 and q1 were detected before


def test_the_keypoint_store_keeps_sifts_descriptors_as_bytes_and_gives_the_same_floats() -> None:
    """SIFT's float descriptors are whole numbers 0-255: the process's store keeps them as bytes
    (a quarter of the memory) and gives back the floats ``detect`` found, every time."""
    from harness.localizers import keypoints as kp

    gray = _texture(np.random.default_rng(5), 240, 320)
    kc = KeypointConfig()
    xy, d = kp.detect(gray, kc)
    assert d is not None and d.dtype == np.float32 and len(d) > 50
    before = kp._stored[0]
    first, again = kp.stored_keypoints(gray, kc), kp.stored_keypoints(gray.copy(), kc)
    for got in (first, again):
        assert got[1] is not None and got[1].dtype == np.float32
        assert got[0].tobytes() == xy.tobytes() and got[1].tobytes() == d.tobytes()
    assert kp._stored[0] - before == xy.nbytes + d.nbytes // 4  # one entry, its descriptors bytes


def test_every_box_at_once_shares_as_one_box_at_a_time_bit_for_bit() -> None:
    """Each box's mean share, taken for a frame's boxes together, is the one taken a box at a
    time (the integral sums in the same order, over the box's covering pixels): boxes inside,
    across and outside the frame, and empty ones (NaN)."""
    from harness.localizers.keypoints import box_shares

    rng = np.random.default_rng(2)
    for _ in range(20):
        h, w = int(rng.integers(3, 90)), int(rng.integers(3, 120))
        smap = rng.random((h, w)).astype(np.float32)
        a = rng.uniform(-15, max(h, w) + 5, (50, 2))
        boxes = np.c_[a, a + rng.uniform(0, 50, (50, 2)) * (rng.random((50, 1)) < 0.9)]
        ii = cv2.integral(smap.astype(np.float64))
        want = np.full(len(boxes), np.nan)
        for i, (x1, y1, x2, y2) in enumerate(boxes):
            p, q = int(np.clip(np.floor(x1), 0, w)), int(np.clip(np.floor(y1), 0, h))
            u, v = int(np.clip(np.ceil(x2), 0, w)), int(np.clip(np.ceil(y2), 0, h))
            if u > p and v > q:
                want[i] = (ii[v, u] - ii[q, u] - ii[v, p] + ii[q, p]) / float((u - p) * (v - q))
        assert box_shares(smap, boxes).tobytes() == want.tobytes()

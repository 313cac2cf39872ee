"""The plain difference of a registered pair (docs/decisions.md, *The plain difference*).

The synthetic pair of tests/localizers/test_keypoints.py, whose truth is known: a textured scene
seen twice with a shift of (7, 4) px and a new object pasted into the second view. Registration
finds that shift and calls the pair comparable; the difference is near zero on the background,
highest on the object, blind to the map's gain and offset, and NaN where the map does not reach.
Frames of two unrelated scenes are not comparable, and say why; the fallback compares them
without keypoints.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from harness.detect.colour import colour_novelty
from harness.detect.config import DifferenceConfig, check_difference
from harness.detect.difference import (
    box_differences,
    difference_contrast,
    difference_map,
    register,
)
from harness.errors import ConfigError
from harness.localizers.config import KeypointConfig, LocalConfig

from ..localizers.test_keypoints import OBJECT, _background_boxes, _pair, _texture

cv2 = pytest.importorskip("cv2")


def _rgb(g: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(g, cv2.COLOR_GRAY2RGB)


def test_a_shifted_pair_registers_by_its_shift_and_its_difference_is_the_new_object() -> None:
    q, m = (_rgb(x) for x in _pair())
    dc = DifferenceConfig()
    reg = register(q, m, KeypointConfig(), dc)
    assert reg.comparable and reg.why == "" and reg.method == "homography"
    assert reg.inliers >= 30 and reg.footprint > 0.95
    # a map pixel (x, y) is the query's (x - 7, y - 4)
    moved = cv2.perspectiveTransform(np.array([[[100.0, 100.0]]]), reg.H).ravel()
    np.testing.assert_allclose(moved, [93.0, 96.0], atol=0.5)
    made = difference_map(q, m, reg, dc)
    assert made is not None
    d, scale = made
    assert scale == 1.0 and d.shape == q.shape[:2]
    # the map does not reach the query's last 7 columns and 4 rows: left out, never a change
    assert np.isnan(d[:, -3:]).all() and np.isnan(d[-2:, :]).all()
    assert np.isfinite(d[:-8, :-8]).all()
    boxes = np.vstack([np.array(OBJECT, np.float64), _background_boxes()])
    for score in ("contrast", "ratio"):
        c = difference_contrast(d, scale, boxes, dataclasses.replace(dc, box_score=score))
        assert c[0] > 3 * max(c[1:].max(), 1.0 if score == "ratio" else 0.5), (score, c)
    # the background of a registered pair differs by a few colour units, the object by tens
    x1, y1, x2, y2 = OBJECT
    assert np.nanmedian(d[y1:y2, x1:x2]) > 4 * np.nanmedian(d[:200, :200])


def test_gain_and_offset_are_no_change() -> None:
    q, m = (_rgb(x) for x in _pair())
    dc = DifferenceConfig()
    dim = np.clip(m.astype(np.float32) * 0.6 + 20, 0, 255).astype(np.uint8)
    reg = register(q, dim, KeypointConfig(), dc)
    made = difference_map(q, dim, reg, dc)
    assert reg.comparable and made is not None
    boxes = np.vstack([np.array(OBJECT, np.float64), _background_boxes()])
    c = difference_contrast(*made, boxes)
    assert c[0] > 3 * max(c[1:].max(), 0.5), c


def test_sizes_are_shares_of_the_frame() -> None:
    """The same pair at twice the size: the same registration, the same ranking of the boxes."""
    q, m = (_rgb(x) for x in _pair())
    q2, m2 = (cv2.resize(x, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC) for x in (q, m))
    dc = dataclasses.replace(DifferenceConfig(), side=2000, register_side=2000)
    reg = register(q2, m2, KeypointConfig(), dc)
    moved = cv2.perspectiveTransform(np.array([[[200.0, 200.0]]]), reg.H).ravel()
    np.testing.assert_allclose(moved, [186.0, 192.0], atol=1.0)
    made = difference_map(q2, m2, reg, dc)
    assert made is not None
    boxes = np.vstack([np.array(OBJECT, np.float64), _background_boxes()]) * 2
    c = difference_contrast(*made, boxes)
    assert c[0] > 3 * max(c[1:].max(), 0.5), c


def test_two_unrelated_scenes_are_not_comparable_and_say_why() -> None:
    q = _rgb(_texture(np.random.default_rng(1), 360, 480))
    m = _rgb(_texture(np.random.default_rng(2), 360, 480))
    dc = DifferenceConfig()
    reg = register(q, m, KeypointConfig(), dc)
    assert not reg.comparable
    assert reg.why.startswith(("too few matches", "too few inliers", "a degenerate warp"))
    assert difference_map(q, m, reg, dc) is None  # nothing compared, nothing scored
    fb = reg.fallback(q, m, dc, LocalConfig())
    # a fallback compares the pair but is no registration: it keeps the reason, never comparable
    assert not fb.comparable and fb.compares and fb.why == reg.why
    assert fb.method in ("ecc", "identity")
    made = difference_map(q, m, fb, dc)
    assert made is not None and np.isfinite(made[0]).mean() > 0.5
    # the fallback's fit reads the run's [detect.local]: no correlation passes a floor above 1
    strict = reg.fallback(q, m, dc, dataclasses.replace(LocalConfig(), ecc_min_cc=1.01))
    assert strict.method == "identity" and strict.compares and not strict.comparable
    # a blank map frame: no keypoint at all
    blank = np.full_like(m, 128)
    reg = register(q, blank, KeypointConfig(), dc)
    assert not reg.comparable and reg.why.startswith("too few matches")


def test_the_contrast_at_every_ring_is_the_one_integral_sum() -> None:
    """``box_score = "contrast"`` reads the same sums at every ring: at a ring of half the box it
    equals the LoC map's own contrast (:func:`harness.detect.boxes.inside_score`), to float32."""
    from harness.detect.boxes import inside_score

    rng = np.random.default_rng(3)
    d = rng.random((60, 80)).astype(np.float32)
    d[:5] = np.nan  # pixels the map does not reach
    a = rng.uniform(0, 70, (40, 2))
    boxes = np.c_[a, a + rng.uniform(1, 30, (40, 2))]
    dc = dataclasses.replace(DifferenceConfig(), box_score="contrast", ring=0.5)
    got = difference_contrast(d, 1.0, boxes, dc)
    want = [inside_score(d, b, "contrast") for b in boxes]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)  # inside_score sums in float32


def test_bad_difference_settings_are_one_error_naming_the_key() -> None:
    bads = (("min_inliers", 3), ("shift", 0.5), ("box_score", "max"), ("ring", 0),
            ("colour", "hue"), ("colour_bins", (8, 16)), ("colour_bins", (1, 16, 16)),
            ("colour_side", 8))  # fmt: skip
    for key, bad in bads:
        with pytest.raises(ConfigError, match=key):
            check_difference(dataclasses.replace(DifferenceConfig(), **{key: bad}), "[x]")


def test_a_registration_as_the_null_draws_its_moves() -> None:
    """The shifted pair's registration as a perturbed copy's shift, rotation and scale; a copy
    drawn from it moves the map frame as the pair moved (docs/decisions.md, *Calibrated alarms*)."""
    from harness.detect.config import NullConfig
    from harness.detect.null import draw
    from harness.perturb import apply

    q, m = (_rgb(x) for x in _pair())
    reg = register(q, m, KeypointConfig(), DifferenceConfig())
    dx, dy, rot, sc = reg.similarity(q.shape[1], q.shape[0])
    np.testing.assert_allclose([dx * 480, dy * 360, rot, sc], [-7, -4, 0, 1], atol=0.3)
    assert 0 <= reg.residual < 0.002  # a pure shift: the homography leaves nothing (no parallax)
    moves = np.array([[dx, dy, rot, sc, reg.residual]])
    p = draw(NullConfig(gain=0, offset=0, blur=0, jpeg_quality=0), 0, moves)
    assert (p.dx, p.dy, p.rotation_deg, p.scale) == pytest.approx((dx, dy, rot, sc), abs=1e-4)
    assert p.wobble == pytest.approx(reg.residual, abs=1e-6)
    copy = apply(m, p)  # the map frame moved as the query frame is: the same background
    diff = np.abs(copy.astype(int) - q.astype(int)).max(axis=2)
    x1, y1, x2, y2 = OBJECT
    diff[y1:y2, x1:x2] = 0  # the pasted object is the change
    assert np.median(diff[20:-20, 20:-20]) <= 2 and np.mean(diff[20:-20, 20:-20] > 30) < 0.02


def test_a_wobbled_copy_moves_by_its_rms_and_is_named_by_its_values() -> None:
    """A copy's ``wobble`` (the parallax a homography leaves; docs/decisions.md, *Calibrated
    alarms*): a smooth displacement of that RMS share of the diagonal, the same bytes wherever the
    same fragment is read; a copy without one has no ``w`` part in its name."""
    from harness.perturb import Perturbation, apply, fragment, parse

    _, m = (_rgb(x) for x in _pair())
    still = Perturbation(dx=0.01)
    assert ",w" not in fragment(still) and parse(fragment(still).split("=", 1)[1]) == still
    with pytest.raises(ValueError, match=r"wobble -0\.1 must be >= 0"):
        parse("g1,w-0.1")
    p = Perturbation(wobble=0.005)
    assert fragment(p).endswith(",w0.005") and parse(fragment(p).split("=", 1)[1]) == p
    a, b = apply(m, p), apply(m, p)
    assert np.array_equal(a, b) and not np.array_equal(a, m)
    # the displacement's size: dense optical flow from the original to the copy, inside borders
    g0, g1 = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (m, a))
    flow = cv2.calcOpticalFlowFarneback(g0, g1, None, 0.5, 3, 21, 3, 5, 1.1, 0)
    rms = float(np.sqrt((flow[30:-30, 30:-30] ** 2).sum(axis=2).mean()))
    diag = float(np.hypot(*m.shape[:2]))
    assert 0.5 * 0.005 * diag < rms < 1.5 * 0.005 * diag, (rms, 0.005 * diag)


def test_a_new_colour_is_novel_from_any_view_and_a_frame_against_itself_is_not() -> None:
    """The colours' novelty (docs/decisions.md, *The colours' novelty*) needs no registration: a red
    square put into a grey textured scene is the novel place of the new frame, even against a
    map frame that shows the scene from elsewhere (flipped, so no warp could carry it), and a
    frame against itself holds no novel colour at all."""
    q, m = (_rgb(x) for x in _pair())
    x1, y1, x2, y2 = OBJECT
    q = q.copy()
    q[y1:y2, x1:x2] = (200, 30, 30)
    dc = DifferenceConfig()
    elsewhere = np.ascontiguousarray(m[::-1, ::-1])
    nov, f = colour_novelty(q, elsewhere, dc)
    assert nov.shape == (round(q.shape[0] * f), round(q.shape[1] * f))
    boxes = np.vstack([np.array(OBJECT, np.float64), _background_boxes()])
    sc = difference_contrast(nov, f, boxes, dc)
    assert sc[0] > 3 * max(sc[1:].max(), 1e-3), sc
    same, _ = colour_novelty(q, q, dc)
    assert float(same.max()) < 1e-6
    # a box's plain-difference score: its difference times its novelty, both floored at 0;
    # without novelty, the difference alone; compared by nothing, none
    made = difference_map(q, m, register(q, m, KeypointConfig(), dc), dc)
    assert made is not None
    both = box_differences(made, (nov, f), boxes, dc)
    np.testing.assert_allclose(
        both, np.maximum(difference_contrast(*made, boxes, dc), 0) * np.maximum(sc, 0)
    )
    np.testing.assert_array_equal(
        box_differences(made, None, boxes, dc), difference_contrast(*made, boxes, dc)
    )
    assert np.isnan(box_differences(None, (nov, f), boxes, dc)).all()


def test_the_colour_statistics_are_numpys_bit_for_bit() -> None:
    """The pair's per-channel mean and spread over the pixels both frames see: the bits of
    ``lab[sel].mean(0)`` and ``lab[sel].std(0)``, on any share of the frame, all of it included."""
    from harness.detect.difference import _mean_std

    rng = np.random.default_rng(0)
    for t in range(62):
        h, w = (480, 640) if t >= 60 else (int(rng.integers(1, 200)), int(rng.integers(1, 200)))
        lab = (rng.random((h, w, 3)) * [100, 255, 255] - [0, 128, 128]).astype(np.float32)
        sel = rng.random((h, w)) < rng.random()
        sel[0, 0] |= t % 5 == 0 or not sel.any()
        if t % 5 == 0:
            sel[:] = True
        mean, std = _mean_std(lab, sel)
        assert mean.dtype == std.dtype == np.float32
        assert mean.tobytes() == lab[sel].mean(0).tobytes()
        assert std.tobytes() == lab[sel].std(0).tobytes()


def _contrast_box_by_box(dmap: np.ndarray, scale: float, boxes: np.ndarray, dc: Any) -> np.ndarray:
    """The box score one box at a time, as the harness took it before it took every box at once."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4) * scale
    ok = np.isfinite(dmap)
    val = cv2.integral(np.where(ok, dmap, 0).astype(np.float64))
    cnt = cv2.integral(ok.astype(np.uint8)).astype(np.float64)
    h, w = dmap.shape

    def sums(x1: float, y1: float, x2: float, y2: float) -> tuple[float, float]:
        u0, u1 = max(int(np.ceil(x1 - 0.5)), 0), min(int(np.ceil(x2 - 0.5)), w)
        v0, v1 = max(int(np.ceil(y1 - 0.5)), 0), min(int(np.ceil(y2 - 0.5)), h)
        if u1 <= u0 or v1 <= v0:
            return 0.0, 0.0
        return (
            val[v1, u1] - val[v0, u1] - val[v1, u0] + val[v0, u0],
            cnt[v1, u1] - cnt[v0, u1] - cnt[v1, u0] + cnt[v0, u0],
        )

    out = np.full(len(b), np.nan)
    for i, (x1, y1, x2, y2) in enumerate(b):
        si, ni = sums(x1, y1, x2, y2)
        if ni <= 0:
            continue
        gw, gh = (x2 - x1) * dc.ring, (y2 - y1) * dc.ring
        so, no = sums(x1 - gw, y1 - gh, x2 + gw, y2 + gh)
        inner = si / ni
        ring = (so - si) / (no - ni) if no > ni else 0.0
        out[i] = inner - ring if dc.box_score == "contrast" else inner / (1.0 + ring)
    return out


def test_every_box_at_once_scores_as_one_box_at_a_time_bit_for_bit() -> None:
    """The box scores of a frame's boxes taken together are the ones taken a box at a time: the
    same float64 sums in the same order, for boxes inside, across and outside the frame, thinner
    than a pixel, on pixels the map does not reach, at both box scores and three rings."""
    rng = np.random.default_rng(5)
    for t in range(30):
        h, w = int(rng.integers(5, 120)), int(rng.integers(5, 160))
        d = rng.random((h, w)).astype(np.float32)
        d[rng.random((h, w)) < 0.2 * (t % 3)] = np.nan
        a = rng.uniform(-20, max(h, w) + 5, (60, 2))
        boxes = np.c_[a, a + rng.uniform(0.01, 60, (60, 2)) * (rng.random((60, 1)) < 0.9)]
        for score, ring in (("contrast", 0.5), ("ratio", 0.25), ("contrast", 0.0)):
            dc = dataclasses.replace(DifferenceConfig(), box_score=score, ring=ring)
            scale = float(rng.choice([1.0, 0.5, 1.7]))
            got = difference_contrast(d, scale, boxes, dc)
            want = _contrast_box_by_box(d, scale, boxes, dc)
            assert got.tobytes() == want.tobytes(), (t, score, ring)


def test_frame_groups_are_pandas_groups_in_order_of_first_appearance() -> None:
    """The detect stage's frames by numpy: the keys and rows of ``groupby(sort=False)``, in the
    order the frames first appear, and none for no rows."""
    import pandas as pd

    from harness.records import QUERY_KEY, frame_groups

    rng = np.random.default_rng(4)
    df = pd.DataFrame({
        "q_session": rng.choice(["2012-01-22", "2012-03-31", "b"], 200),
        "q_camera": rng.choice(["Cam5", "Cam1"], 200),
        "q_utime": rng.integers(0, 9, 200),
    })  # fmt: skip
    want = [((str(a), str(b), int(c)), g.index.to_numpy()) for (a, b, c), g in
            df.groupby(QUERY_KEY, sort=False)]  # fmt: skip
    got = frame_groups(df)
    assert [k for k, _ in got] == [k for k, _ in want]
    assert all(np.array_equal(r, w) for (_, r), (_, w) in zip(got, want, strict=True))
    assert frame_groups(df.iloc[:0]) == []

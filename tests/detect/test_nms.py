"""The detector's NMS keeps exactly the boxes OpenCV's ``dnn.NMSBoxes`` keeps, first ones first."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from harness.boxes import FrameNMS, greedy_nms, nms, suppression


def _opencv(boxes: np.ndarray, loc: np.ndarray, nms_iou: float, max_boxes: int) -> np.ndarray:
    """``dnn.NMSBoxes`` on the finite boxes in descending LoC (ties: the earlier box first)."""
    ok = np.flatnonzero(np.isfinite(loc))
    if not len(ok):
        return np.zeros(0, np.int64)
    order = ok[np.argsort(-loc[ok], kind="stable")]
    b = boxes[order]
    xywh = [(float(x1), float(y1), float(x2 - x1), float(y2 - y1)) for x1, y1, x2, y2 in b]
    rank = (np.arange(len(b), 0, -1) / len(b)).astype(np.float32)
    keep = np.asarray(cv2.dnn.NMSBoxes(xywh, rank.tolist(), 0.0, nms_iou), np.int64).reshape(-1)
    keep = keep[np.argsort(-rank[keep], kind="stable")][:max_boxes]
    return order[keep]


@pytest.mark.parametrize("seed", range(6))
def test_the_kept_boxes_are_opencvs_on_random_sets_with_ties_and_empty_boxes(seed: int) -> None:
    """Random frames of up to 400 boxes: rounded corners (identical boxes and tied scores), boxes
    of no area, NaN scores, thresholds 0.3-1, caps 1, 10 and all: the same indices in the same
    order as OpenCV's, and a cached suppression (Table D's draws) the same again."""
    rng = np.random.default_rng(seed)
    nms = FrameNMS(0.5, 10)
    for t in range(150):
        n = int(rng.integers(0, 400))
        xy, wh = rng.uniform(0, 500, (n, 2)), rng.uniform(0, 200, (n, 2))
        if t % 3 == 0:
            xy, wh = np.round(xy), np.round(wh)
        if t % 5 == 0 and n:
            wh[rng.integers(0, n, max(1, n // 5))] = 0.0
        boxes = np.c_[xy, xy + wh]
        loc = np.round(rng.random(n), 2 if t % 2 else 12)
        if t % 4 == 0 and n:
            loc[rng.integers(0, n, max(1, n // 10))] = np.nan
        thr = float(rng.choice([0.3, 0.45, 0.5, 0.7, 0.9, 1.0]))
        for cap in (1, 10, 1000):
            want = _opencv(boxes, loc, thr, cap)
            assert greedy_nms(boxes, loc, thr, cap).tolist() == want.tolist(), (t, thr, cap)
        sup = suppression(boxes, 0.5)
        assert greedy_nms(boxes, loc, 0.5, 10, sup).tolist() == nms(boxes, loc).tolist()
        assert nms(boxes, loc).tolist() == _opencv(boxes, loc, 0.5, 10).tolist()


@pytest.mark.parametrize("seed", range(3))
def test_many_score_rows_keep_what_each_row_keeps_alone(seed: int) -> None:
    """``FrameNMS.many`` (Table D's draws, all at once): row by row the indices, in the order, of
    one call per row, on boxes with repeats, no area and rounded corners, at caps 1, 10, 100."""
    rng = np.random.default_rng(seed)
    for t in range(40):
        n = int(rng.integers(0, 120))
        xy, wh = np.round(rng.uniform(0, 300, (n, 2))), np.round(rng.uniform(0, 120, (n, 2)))
        if t % 4 == 0 and n:
            wh[rng.integers(0, n, max(1, n // 4))] = 0.0
        boxes = np.c_[xy, xy + wh]
        if n > 2:
            boxes[1] = boxes[0]
        nms = FrameNMS(float(rng.choice([0.3, 0.5, 1.0])), int(rng.choice([1, 10, 100])))
        scores = np.round(rng.random((25, n)), 1 if t % 2 else 6)  # ties within a row
        kept = nms.many(boxes, scores)
        for row, k in zip(scores, kept, strict=True):
            np.testing.assert_array_equal(k[k >= 0], nms(boxes, row))
            assert (k[k < 0] == -1).all() and (np.diff(np.flatnonzero(k < 0)) == 1).all()


@pytest.mark.parametrize("seed", range(3))
def test_nms_and_greedy_nms_keep_the_same_boxes(seed: int) -> None:
    """The one NMS in its two forms: OpenCV's call (``nms``, a box set scored once) and the same
    suppression on an overlap matrix made once (``greedy_nms``), on random frames of up to 400 boxes
    with scores distinct in float32 (OpenCV's score type), at thresholds 0.3-0.9 and caps 1-1000."""
    rng = np.random.default_rng(seed)
    for t in range(60):
        n = int(rng.integers(0, 400))
        xy, wh = rng.uniform(0, 500, (n, 2)), rng.uniform(1, 200, (n, 2))
        boxes = np.c_[xy, xy + wh]
        scores = rng.permutation(n).astype(np.float64) / max(n, 1)
        thr = float(rng.choice([0.3, 0.5, 0.7, 0.9]))
        for cap in (1, 10, 1000):
            assert (
                nms(boxes, scores, thr)[:cap].tolist()
                == greedy_nms(boxes, scores, thr, cap).tolist()
            ), (t, thr, cap)

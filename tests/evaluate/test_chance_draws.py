"""Table D's chance draws give the same APs whether each frame's draws go through NMS together."""

from __future__ import annotations

import numpy as np
import pytest

from harness.boxes import FrameNMS, iou_matrix
from harness.evaluate.box_ap import match50, match50_rows
from harness.evaluate.table_d_chance import _random_score_aps


class _OneAtATime:
    """The same NMS without ``many``: the draws one score set at a time."""

    def __init__(self, nms: FrameNMS) -> None:
        self.nms = nms

    def __call__(self, boxes: np.ndarray, scores: np.ndarray) -> np.ndarray:
        return self.nms(boxes, scores)


def _world(rng: np.random.Generator) -> tuple[dict, dict]:
    cands, gts = {}, {}
    for i in range(int(rng.integers(1, 8))):
        n = int(rng.integers(0, 60))
        xy = rng.integers(0, 50, (n, 2)).astype(float)
        cands[i] = np.hstack([xy, xy + rng.integers(0, 30, (n, 2))])
        if n > 3:
            cands[i][1] = cands[i][0]  # a repeated box
        g = int(rng.integers(0, 4))  # frames without a change box too
        gx = rng.integers(0, 50, (g, 2)).astype(float)
        gts[i] = np.hstack([gx, gx + rng.integers(1, 30, (g, 2))])
        if g > 1 and n:
            gts[i][0] = gts[i][1] = cands[i][0]  # equal IoUs: the last of equals is taken
    return cands, gts


@pytest.mark.parametrize("seed", range(4))
def test_draws_together_give_the_aps_of_draws_one_by_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for trial in range(15):
        cands, gts = _world(rng)
        ids, n_gt = sorted(gts), sum(len(v) for v in gts.values())
        nms = FrameNMS(float(rng.choice([0.3, 0.5, 0.7, 1.0])), int(rng.choice([1, 3, 10, 100])))
        together = _random_score_aps(cands, gts, nms, ids, n_gt, 40, np.random.default_rng(trial))
        one = _random_score_aps(
            cands, gts, _OneAtATime(nms), ids, n_gt, 40, np.random.default_rng(trial)
        )
        np.testing.assert_array_equal(together, one)
        if n_gt:
            assert np.isfinite(together).all()


def test_rows_of_matches_are_match50_row_by_row() -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        n, g = int(rng.integers(1, 30)), int(rng.integers(0, 5))
        a = rng.integers(0, 40, (n, 2)).astype(float)
        boxes = np.hstack([a, a + rng.integers(1, 20, (n, 2))])
        gt = boxes[rng.integers(0, n, g)] + rng.integers(-2, 3, (g, 4))
        iou = iou_matrix(boxes, gt)
        kept = np.full((10, 6), -1)
        for r in range(10):
            k = rng.permutation(n)[: int(rng.integers(0, 7))]
            kept[r, : len(k)] = k
        got = match50_rows(iou, kept)
        for r in range(10):
            k = kept[r][kept[r] >= 0]
            np.testing.assert_array_equal(got[r, : len(k)], match50(iou[k], np.arange(len(k))))
            assert not got[r, len(k) :].any()

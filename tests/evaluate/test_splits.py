"""RoC/SoB labels: hand-computed cases and properties."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from harness.evaluate.config import SplitsConfig
from harness.evaluate.splits import LEFT_OUT, NEGATIVE, POSITIVE, label, paper_splits, roc_sob


def test_overlapping_change_boxes_are_not_double_counted() -> None:
    change = np.array([[0, 0, 10, 10], [5, 0, 15, 10]], float)  # union area 150, overlap 50
    roc, sob = roc_sob(np.array([[0, 0, 20, 10]], float), change, 20, 20)
    assert roc[0] == 150 / 200 and sob[0] == 200 / 400


def test_three_overlapping_change_boxes() -> None:
    change = np.array([[0, 0, 4, 4], [2, 2, 6, 6], [3, 0, 5, 3]], float)
    # union: 16 + 16 - 4 (b0∩b1) + 6 - 2 (b0∩b2: x3..4,y0..3 -> 3) ... count by grid instead
    grid = np.zeros((6, 6), bool)
    for x1, y1, x2, y2 in change.astype(int):
        grid[y1:y2, x1:x2] = True
    roc, _ = roc_sob(np.array([[0, 0, 6, 6]], float), change, 6, 6)
    assert roc[0] == grid.sum() / 36


def test_no_change_frame_has_zero_roc() -> None:
    roc, sob = roc_sob(np.array([[0, 0, 5, 5]], float), np.zeros((0, 4)), 10, 10)
    assert roc[0] == 0 and sob[0] == 0.25


def test_paper_splits_and_labels() -> None:
    splits = paper_splits(SplitsConfig())
    assert [s.roc_max for s in splits] == [0.01, 0.02, 0.03, 0.04, 0.05]
    sp = splits[2]
    roc = np.array([0.95, 0.95, 0.02, 0.02, 0.5])
    sob = np.array([0.1, 0.5, 0.5, 0.1, 0.5])
    assert label(roc, sob, sp).tolist() == [POSITIVE, LEFT_OUT, NEGATIVE, LEFT_OUT, LEFT_OUT]


boxes = st.tuples(st.floats(0, 90), st.floats(0, 90), st.floats(1, 50), st.floats(1, 50)).map(
    lambda t: (t[0], t[1], t[0] + t[2], t[1] + t[3])
)


@settings(max_examples=60, deadline=None)
@given(st.lists(boxes, min_size=1, max_size=6), st.lists(boxes, min_size=0, max_size=4))
def test_roc_and_sob_lie_in_unit_interval(samples: list, change: list) -> None:
    roc, sob = roc_sob(np.array(samples), np.array(change).reshape(-1, 4), 140, 140)
    assert ((roc >= 0) & (roc <= 1)).all() and ((sob > 0) & (sob <= 1)).all()


@settings(max_examples=60, deadline=None)
@given(
    boxes,
    st.lists(boxes, min_size=0, max_size=3),
    st.floats(0, 1),
    st.floats(0, 1),
    st.floats(0, 1),
    st.floats(0, 1),
)
def test_box_inside_a_change_box_has_roc_one(
    outer: tuple, others: list, a: float, b: float, c: float, d: float
) -> None:
    x1, y1, x2, y2 = outer
    w, h = x2 - x1, y2 - y1
    ix1, iy1 = x1 + a * w * 0.5, y1 + b * h * 0.5
    inner = (ix1, iy1, ix1 + max(0.5, c * (x2 - ix1)), iy1 + max(0.5, d * (y2 - iy1)))
    inner = (inner[0], inner[1], min(inner[2], x2), min(inner[3], y2))
    if inner[2] <= inner[0] or inner[3] <= inner[1]:
        return
    roc, _ = roc_sob(np.array([inner]), np.array([outer, *others]).reshape(-1, 4), 200, 200)
    assert abs(roc[0] - 1.0) < 1e-9

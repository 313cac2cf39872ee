"""Fusion (SPEC section 7) and the 101-point AP (section 9): hand-computed cases and properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from harness.fusion import fuse, intersection_closure, loc_map
from harness.metrics import average_precision, bootstrap_ap

# Three boxes: A=[0,10]x[0,10], B=[5,15]x[5,15], C=[8,20]x[0,8]
BOXES = np.array([[0, 0, 10, 10], [5, 5, 15, 15], [8, 0, 20, 8]], float)
R = np.array([0.1, 0.5, 1.0])
D = np.array([1.0, 2.0, 3.0])
# closure: A, B, C, A∩B=[5,5,10,10], A∩C=[8,0,10,8], B∩C=[8,5,15,8], A∩B∩C=[8,5,10,8]
CLOSURE = {(0, 0, 10, 10): "A", (5, 5, 15, 15): "B", (8, 0, 20, 8): "C", (5, 5, 10, 10): "AB", (8, 0, 10, 8): "AC", (8, 5, 15, 8): "BC", (8, 5, 10, 8): "ABC"}


def _by_cover(boxes: np.ndarray, loc: np.ndarray) -> dict[str, float]:
    return {CLOSURE[tuple(b)]: v for b, v in zip(boxes.astype(int).tolist(), loc, strict=True)}


def test_closure_of_three_boxes() -> None:
    fused, capped = intersection_closure(BOXES)
    assert {tuple(b) for b in fused.astype(int).tolist()} == set(CLOSURE) and not capped


def test_rank_fusion_by_hand() -> None:
    got = _by_cover(*fuse(BOXES, R, D, "rank_fusion"))
    inv = {"A": 10, "B": 2, "C": 1}
    for cov, v in got.items():
        n, s = len(cov), sum(inv[c] for c in cov)
        assert v == pytest.approx(1 / (n * s))
    assert got["ABC"] == pytest.approx(1 / 39) and got["A"] == pytest.approx(0.1)


def test_rank_fusion_le2_uses_two_of_three() -> None:
    got = _by_cover(*fuse(BOXES, R, D, "rank_fusion_le2", seed=3))
    inv = {"A": 10, "B": 2, "C": 1}
    assert any(got["ABC"] == pytest.approx(1 / (2 * (inv[a] + inv[b]))) for a, b in ("AB", "AC", "BC"))
    assert got["AB"] == pytest.approx(1 / 24)  # two covers: unchanged
    assert _by_cover(*fuse(BOXES, R, D, "rank_fusion_le2", seed=3))["ABC"] == got["ABC"]  # seeded
    assert _by_cover(*fuse(BOXES, R, D, "rank_fusion_le3"))["ABC"] == pytest.approx(1 / 39)


def test_score_methods_and_no_fusion_by_hand() -> None:
    mx = _by_cover(*fuse(BOXES, R, D, "score_max"))
    sm = _by_cover(*fuse(BOXES, R, D, "score_sum"))
    assert mx == {"A": 1, "B": 2, "C": 3, "AB": 2, "AC": 3, "BC": 3, "ABC": 3}
    assert sm == {"A": 1, "B": 2, "C": 3, "AB": 3, "AC": 4, "BC": 5, "ABC": 6}
    b, loc = fuse(BOXES, R, D, "rank_no_fusion")
    assert np.array_equal(b, BOXES) and np.array_equal(loc, R)


def test_loc_map_takes_the_smallest_covering_box() -> None:
    fused, loc = fuse(BOXES, R, D, "score_sum")
    m = loc_map(fused, loc, 22, 16)
    assert m[6, 9] == 6  # inside A∩B∩C
    assert m[2, 2] == 1 and m[12, 12] == 2 and m[2, 18] == 3
    assert np.isnan(m[14, 20]) and np.isnan(m[0, 21])


box_st = st.tuples(st.integers(0, 30), st.integers(0, 30), st.integers(1, 20), st.integers(1, 20)).map(lambda t: (t[0], t[1], t[0] + t[2], t[1] + t[3]))


@settings(max_examples=50, deadline=None)
@given(st.lists(box_st, min_size=1, max_size=6, unique=True), st.data())
def test_rank_fusion_equals_r_where_one_box_covers(boxes: list, data: st.DataObject) -> None:
    b = np.array(boxes, float)
    r = np.array(data.draw(st.lists(st.floats(0.01, 1), min_size=len(b), max_size=len(b))))
    fused, loc = fuse(b, r, np.ones(len(b)), "rank_fusion")
    from harness.fusion import cover_matrix

    cov = cover_matrix(fused, b)
    one = cov.sum(1) == 1
    np.testing.assert_allclose(loc[one], r[cov[one].argmax(1)])
    assert (loc > 0).all() and (loc <= 1).all()


def test_ap_by_hand_with_ties() -> None:
    # scores desc: 0.9(+) 0.8(-) 0.7(+) 0.1(-): P@R.5 = 1, P@R1 = 2/3
    assert average_precision([1, 0, 1, 0], [0.9, 0.8, 0.7, 0.1]) == pytest.approx((51 * 1 + 50 * 2 / 3) / 101)
    # all tied: one point, precision 2/3 at recall 1
    assert average_precision([1, 1, 0], [0.5, 0.5, 0.5]) == pytest.approx(2 / 3)
    # a tie between a positive and a negative enters together
    assert average_precision([1, 0, 1], [0.9, 0.5, 0.5]) == pytest.approx((51 * 1 + 50 * 2 / 3) / 101)
    assert np.isnan(average_precision([0, 0], [0.3, 0.2]))
    assert average_precision([1, 1], [0.3, 0.2]) == 1.0


def test_recall_grid_tolerance() -> None:
    # 29 of 100 positives first: recall 0.29 must reach R = 0.29
    labels = np.r_[np.ones(29), np.zeros(1), np.ones(71)]
    scores = -np.arange(len(labels), dtype=float)
    ap = average_precision(labels, scores)
    assert ap > 0.99


# scores on a 0.1 grid, so that the transforms below keep distinct values distinct in floating point
labels_scores = st.integers(2, 40).flatmap(lambda n: st.tuples(st.lists(st.booleans(), min_size=n, max_size=n), st.lists(st.integers(-50, 50).map(lambda k: k / 10), min_size=n, max_size=n)))


@settings(max_examples=80, deadline=None)
@given(labels_scores)
def test_ap_in_unit_interval_and_invariant_to_monotone_transforms(ls: tuple) -> None:
    y, s = np.array(ls[0]), np.array(ls[1])
    ap = average_precision(y, s)
    if not y.any():
        assert np.isnan(ap)
        return
    assert 0 <= ap <= 1
    assert average_precision(y, np.exp(s)) == pytest.approx(ap)
    assert average_precision(y, 3 * s + 7) == pytest.approx(ap)


def test_bootstrap_interval_brackets_ap() -> None:
    rng = np.random.default_rng(0)
    y = rng.random(400) < 0.3
    s = y + rng.normal(0, 0.8, 400)
    groups = np.repeat(np.arange(40), 10)
    lo, hi = bootstrap_ap(y, s, groups, 200, 0.95, 0)
    ap = average_precision(y, s)
    assert lo < ap < hi and hi - lo < 0.4
    assert bootstrap_ap(y, s, groups, 200, 0.95, 0) == (lo, hi)

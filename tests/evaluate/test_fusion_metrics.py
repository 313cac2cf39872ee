"""Fusion (method §7) and the 101-point AP (section 9): hand-computed cases and properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from harness.evaluate.metrics import (
    average_precision,
    bootstrap_aps,
    interval,
    resample_counts,
)
from harness.fusion.fuse import SMALL_CLOSURE, fuse, intersection_closure, loc_map, rows_of

# Three boxes: A=[0,10]x[0,10], B=[5,15]x[5,15], C=[8,20]x[0,8]
BOXES = np.array([[0, 0, 10, 10], [5, 5, 15, 15], [8, 0, 20, 8]], float)
R = np.array([0.1, 0.5, 1.0])
D = np.array([1.0, 2.0, 3.0])
# closure: A, B, C, A∩B=[5,5,10,10], A∩C=[8,0,10,8], B∩C=[8,5,15,8], A∩B∩C=[8,5,10,8]
CLOSURE = {
    (0, 0, 10, 10): "A",
    (5, 5, 15, 15): "B",
    (8, 0, 20, 8): "C",
    (5, 5, 10, 10): "AB",
    (8, 0, 10, 8): "AC",
    (8, 5, 15, 8): "BC",
    (8, 5, 10, 8): "ABC",
}


def _by_cover(boxes: np.ndarray, loc: np.ndarray) -> dict[str, float]:
    return {CLOSURE[tuple(b)]: v for b, v in zip(boxes.astype(int).tolist(), loc, strict=True)}


def test_closure_of_three_boxes() -> None:
    fused, capped = intersection_closure(BOXES)
    assert {tuple(b) for b in fused.astype(int).tolist()} == set(CLOSURE) and not capped
    # each original (and a repeated one) found at its row, a box of no area named as missing
    boxes = np.vstack([BOXES, BOXES[:1]])
    assert [CLOSURE[tuple(b)] for b in fused[rows_of(fused, boxes)].astype(int).tolist()] == [
        "A",
        "B",
        "C",
        "A",
    ]
    with pytest.raises(ValueError, match=r"box \[3.0, 3.0, 3.0, 9.0\] is not in the closure"):
        rows_of(fused, np.array([[3.0, 3.0, 3.0, 9.0]]))
    with pytest.raises(ValueError, match="is not in the closure"):
        rows_of(fused, np.array([[30.0, 30.0, 40.0, 40.0]]))  # past the last row


# Rank lists of length L = 10: ranks 1, 5, 10 (r = rank / L); r' = (L + 1 - rank) / L = 1.0, 0.6,
# 0.1
L10 = np.array([10, 10, 10])
INV_RD = {"A": 1.0, "B": 10 / 6, "C": 10.0}  # 1 / r'


def test_rank_fusion_by_hand() -> None:
    """method §7: LoC = N * sum 1/r' (the paper's descending order), written out per fused box."""
    got = _by_cover(*fuse(BOXES, R, D, "rank_fusion", L=L10))
    want = {
        "A": 1.0,
        "B": 10 / 6,
        "C": 10.0,
        "AB": 2 * (1 + 10 / 6),
        "AC": 2 * (1 + 10),
        "BC": 2 * (10 / 6 + 10),
        "ABC": 3 * (1 + 10 / 6 + 10),
    }
    assert got == pytest.approx(want)
    assert got["ABC"] == pytest.approx(38.0) and got["A"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="needs the rank-list lengths"):
        fuse(BOXES, R, D, "rank_fusion")


def test_paper_variants_by_hand() -> None:
    """Variant 2 (ascending): 1 / (N * sum 1/r); variant 1 (raw): N * sum 1 / (L + 1 - rank)."""
    asc = _by_cover(*fuse(BOXES, R, D, "rank_fusion_asc"))
    assert (
        asc["A"] == pytest.approx(0.1)
        and asc["AB"] == pytest.approx(1 / 24)
        and asc["ABC"] == pytest.approx(1 / 39)
    )
    raw = _by_cover(*fuse(BOXES, R, D, "rank_fusion_raw", L=L10))
    # L + 1 - rank = 10, 6, 1
    assert raw["A"] == pytest.approx(0.1) and raw["C"] == pytest.approx(1.0)
    assert raw["ABC"] == pytest.approx(3 * (0.1 + 1 / 6 + 1.0)) and raw["BC"] == pytest.approx(
        2 * (1 / 6 + 1.0)
    )


def test_baselines_by_hand() -> None:
    from harness.fusion.fuse import image_loc

    cc = _by_cover(*fuse(BOXES, R, D, "cover_count"))
    assert cc == {"A": 1, "B": 1, "C": 1, "AB": 2, "AC": 2, "BC": 2, "ABC": 3}
    fused, _ = intersection_closure(BOXES)
    sp = _by_cover(fused, image_loc(fused, "size_prior", 22, 16, seed=0))
    assert (
        sp["A"] == pytest.approx(1 - 100 / 352)
        and sp["ABC"] == pytest.approx(1 - 6 / 352)
        and sp["C"] == pytest.approx(1 - 96 / 352)
    )
    r1, r2 = image_loc(fused, "random", 22, 16, seed=7), image_loc(fused, "random", 22, 16, seed=7)
    assert (
        np.array_equal(r1, r2) and ((r1 >= 0) & (r1 < 1)).all() and len(set(r1.tolist())) == len(r1)
    )
    assert not np.array_equal(r1, image_loc(fused, "random", 22, 16, seed=8))
    with pytest.raises(ValueError, match="image_loc"):
        fuse(BOXES, R, D, "size_prior")


def test_rank_fusion_le2_uses_two_of_three() -> None:
    got = _by_cover(*fuse(BOXES, R, D, "rank_fusion_le2", seed=3, L=L10))
    assert any(
        got["ABC"] == pytest.approx(2 * (INV_RD[a] + INV_RD[b])) for a, b in ("AB", "AC", "BC")
    )
    assert got["AB"] == pytest.approx(2 * (1 + 10 / 6))  # two covers: unchanged
    assert (
        _by_cover(*fuse(BOXES, R, D, "rank_fusion_le2", seed=3, L=L10))["ABC"] == got["ABC"]
    )  # seeded
    assert _by_cover(*fuse(BOXES, R, D, "rank_fusion_le3", L=L10))["ABC"] == pytest.approx(38.0)


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


box_st = st.tuples(
    st.integers(0, 30), st.integers(0, 30), st.integers(1, 20), st.integers(1, 20)
).map(lambda t: (t[0], t[1], t[0] + t[2], t[1] + t[3]))


@settings(max_examples=50, deadline=None)
@given(st.lists(box_st, min_size=1, max_size=6, unique=True), st.data())
def test_rank_fusion_orders_single_covers_as_r_does(boxes: list, data: st.DataObject) -> None:
    """Where one box covers a sample, rank fusion's LoC is 1/r' = L / (L + 1 - rank).

    Increasing in r.
    """
    b = np.array(boxes, float)
    L = np.array(data.draw(st.lists(st.integers(1, 50), min_size=len(b), max_size=len(b))))
    rank = np.array([data.draw(st.integers(1, int(n))) for n in L])
    r = rank / L
    fused, loc = fuse(b, r, np.ones(len(b)), "rank_fusion", L=L)
    from harness.fusion.fuse import cover_matrix

    cov = cover_matrix(fused, b)
    one = cov.sum(1) == 1
    k = cov[one].argmax(1)
    np.testing.assert_allclose(loc[one], L[k] / (L[k] + 1 - rank[k]))
    assert (loc >= 1 - 1e-12).all()


def test_ap_by_hand_with_ties() -> None:
    # scores desc: 0.9(+) 0.8(-) 0.7(+) 0.1(-): P@R.5 = 1, P@R1 = 2/3
    assert average_precision([1, 0, 1, 0], [0.9, 0.8, 0.7, 0.1]) == pytest.approx(
        (51 * 1 + 50 * 2 / 3) / 101
    )
    # all tied: one point, precision 2/3 at recall 1
    assert average_precision([1, 1, 0], [0.5, 0.5, 0.5]) == pytest.approx(2 / 3)
    # a tie between a positive and a negative enters together
    assert average_precision([1, 0, 1], [0.9, 0.5, 0.5]) == pytest.approx(
        (51 * 1 + 50 * 2 / 3) / 101
    )
    assert np.isnan(average_precision([0, 0], [0.3, 0.2]))
    assert average_precision([1, 1], [0.3, 0.2]) == 1.0


def test_recall_grid_tolerance() -> None:
    """35 of 100 positives first, then a negative: recall 0.35 = 35/100 must reach R = 0.35,
    although
    np.linspace(0, 1, 101)[35] = 0.35000000000000003 > 35/100 in floating point. Without the
    tolerance, R = 0.35 would take the precision after the negative (100/101 at best)."""
    labels = np.r_[np.ones(35), np.zeros(1), np.ones(65)]
    scores = -np.arange(len(labels), dtype=float)
    assert np.linspace(0, 1, 101)[35] > 35 / 100  # the float trap this test is about
    assert average_precision(labels, scores) == pytest.approx(
        (36 * 1 + 65 * 100 / 101) / 101, abs=1e-12
    )


# scores on a 0.1 grid, so that the transforms below keep distinct values distinct in floating point
labels_scores = st.integers(2, 40).flatmap(
    lambda n: st.tuples(
        st.lists(st.booleans(), min_size=n, max_size=n),
        st.lists(st.integers(-50, 50).map(lambda k: k / 10), min_size=n, max_size=n),
    )
)


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
    groups = np.repeat(np.arange(40), 10)  # 40 query images of 10 samples: whole ones resampled
    counts = resample_counts(40, 200, 0)
    lo, hi = interval(bootstrap_aps(y, s, groups, counts), 0.95)
    ap = average_precision(y, s)
    assert lo < ap < hi and hi - lo < 0.4
    assert interval(bootstrap_aps(y, s, groups, resample_counts(40, 200, 0)), 0.95) == (lo, hi)


def test_resampled_aps_all_rows_at_once_equal_the_weighted_ap_of_each_row() -> None:
    """The bootstrap's AP of every resample (one searchsorted over all rows) equals
    weighted_average_precision of that resample exactly: ties, zero weights, rows without a
    positive (NaN)."""
    from harness.evaluate.metrics import _Ranked, weighted_average_precision

    rng = np.random.default_rng(0)
    for trial in range(200):
        n, rows = int(rng.integers(1, 200)), int(rng.integers(1, 30))
        labels = rng.random(n) < rng.uniform(0.02, 0.6)
        scores = np.round(rng.random(n), int(rng.integers(1, 4)))  # ties
        w = rng.poisson(1.0, (rows, n)).astype(float)
        if trial % 5 == 0:  # one sample only: most rows without a positive
            w[:] = 0
            w[:, rng.integers(0, n)] = 1
        got, pos = _Ranked(labels, scores, np.arange(n)).aps(w)
        for b in range(rows):
            if (w[b] * labels).sum() > 0:
                assert got[b] == weighted_average_precision(labels, scores, w[b]), (trial, b)
                assert pos[b] == (w[b] * labels).sum()
            else:
                assert np.isnan(got[b])


def _closure_by_sorting(boxes: np.ndarray, max_boxes: int | None) -> tuple[np.ndarray, bool]:
    """The closure as the harness computed it before hashing: duplicates found by sorting."""

    def rows(a: np.ndarray) -> np.ndarray:
        a = np.ascontiguousarray(a, np.float64)
        return a.view(np.dtype((np.void, 8 * a.shape[1]))).ravel()

    orig = np.unique(np.asarray(boxes, np.float64).reshape(-1, 4), axis=0)
    orig = orig[(orig[:, 2] > orig[:, 0]) & (orig[:, 3] > orig[:, 1])]
    seen, frontier, capped = orig, orig, False
    while len(frontier):
        x1 = np.maximum(frontier[:, None, 0], orig[None, :, 0])
        y1 = np.maximum(frontier[:, None, 1], orig[None, :, 1])
        x2 = np.minimum(frontier[:, None, 2], orig[None, :, 2])
        y2 = np.minimum(frontier[:, None, 3], orig[None, :, 3])
        cand = np.stack([x1, y1, x2, y2], -1).reshape(-1, 4)
        cand = cand[(cand[:, 2] > cand[:, 0]) & (cand[:, 3] > cand[:, 1])]
        _, first = np.unique(rows(cand), return_index=True)
        new = cand[np.sort(first)]
        new = new[~np.isin(rows(new), rows(seen))]
        new = new[np.lexsort(new.T[::-1])]
        if max_boxes is not None and len(seen) + len(new) > max_boxes:
            new = new[: max(0, max_boxes - len(seen))]
            capped = True
        seen = np.concatenate([seen, new])
        frontier = new
        if capped:
            break
    return np.unique(seen, axis=0).reshape(-1, 4), capped


def test_the_closure_by_hashing_is_the_closure_by_sorting() -> None:
    """Random frames of up to 80 boxes on a coarse grid (many equal corners, so many duplicate
    intersections), capped and not: the same boxes, in the same order, the same cap flag. Half of
    them hold at most ``SMALL_CLOSURE`` boxes, which the closure intersects a pair at a time."""
    rng = np.random.default_rng(0)
    for t in range(80):
        n = int(rng.integers(1, 80 if t < 40 else SMALL_CLOSURE + 1))
        xy = rng.integers(0, 40, (n, 2)).astype(np.float64) * (0.5 if t % 2 else 1.0)
        boxes = np.c_[xy, xy + rng.integers(1, 30, (n, 2))]
        for cap in (None, 3, 12, 50, 4096):
            got, capped = intersection_closure(boxes, cap)
            want, want_capped = _closure_by_sorting(boxes, cap)
            assert np.array_equal(got, want) and capped == want_capped, (t, cap)

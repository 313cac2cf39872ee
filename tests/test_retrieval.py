"""Image-level ranks against a brute-force loop; the faiss engine; imported rank lists."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from harness.errors import RetrievalError
from harness.ranks_import import ranks_from_import
from harness.retrieval import image_ranks, image_ranks_faiss


def brute(
    q: np.ndarray, db: np.ndarray, frame: np.ndarray, gt: np.ndarray, place: list | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SPEC section 6 as a loop.

    d = min over the place, rank = 1 + frames outside it strictly closer, L = 1 + frames outside.
    """
    frames = np.unique(frame)
    rank, dist, Ls = [], [], []
    for i, (qi, g) in enumerate(zip(q, gt, strict=True)):
        members = {int(g)} | (
            {int(f) for f in place[i] if f in frames} if place is not None else set()
        )
        fm = {
            f: np.sqrt(((db[frame == f].astype(np.float64) - qi) ** 2).sum(1)).min() for f in frames
        }
        dq = min(fm[f] for f in members)
        rank.append(1 + sum(1 for f in frames if f not in members and fm[f] < dq))
        dist.append(dq)
        Ls.append(1 + sum(1 for f in frames if f not in members))
    return np.array(rank), np.array(Ls), np.array(dist)


@pytest.mark.parametrize(("chunk", "batch"), [(8192, 1024), (7, 3), (1, 1)])
def test_matches_brute_force_with_several_subimages_per_frame(chunk: int, batch: int) -> None:
    rng = np.random.default_rng(0)
    db = rng.normal(size=(300, 6)).astype(np.float32)
    frame = rng.integers(100, 140, 300)
    q = rng.normal(size=(25, 6)).astype(np.float32)
    gt = rng.choice(np.unique(frame), 25)
    r, L, d = image_ranks(q, db, frame, gt, chunk_rows=chunk, query_batch=batch)
    br, bl, bd = brute(q, db, frame, gt)
    assert np.array_equal(bl, L) and np.array_equal(r, br)
    np.testing.assert_allclose(d, bd, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(("chunk", "batch"), [(8192, 1024), (7, 3)])
def test_place_matches_brute_force(chunk: int, batch: int) -> None:
    rng = np.random.default_rng(2)
    db = rng.normal(size=(300, 6)).astype(np.float32)
    frame = rng.integers(100, 140, 300)
    q = rng.normal(size=(25, 6)).astype(np.float32)
    gt = rng.choice(np.unique(frame), 25)
    # places of 1-4 frames around G, some ids with no database row (ignored)
    place = [
        np.array(sorted({int(g), *rng.integers(95, 145, rng.integers(0, 4)).tolist()})) for g in gt
    ]
    r, L, d = image_ranks(q, db, frame, gt, place, chunk_rows=chunk, query_batch=batch)
    br, bl, bd = brute(q, db, frame, gt, place)
    assert np.array_equal(r, br) and np.array_equal(L, bl)
    np.testing.assert_allclose(d, bd, rtol=1e-6, atol=1e-6)
    assert (len(np.unique(frame)) >= L).all() and (len(np.unique(frame)) > L).any()


def test_place_by_hand() -> None:
    # frames 1..5 on a line, one subimage each; G = 3, place {2, 3}; q is nearest to frame 2, then
    # 1, 4
    db = np.array([[1.0], [2.0], [3.0], [4.0], [5.0]], np.float32)
    frame = np.array([1, 2, 3, 4, 5])
    q = np.array([[1.9]], np.float32)
    r, L, d = image_ranks(
        q, db, frame, np.array([3])
    )  # the single frame: frames 2 (0.1), 1 (0.9) are closer than 3 (1.1)
    assert r.tolist() == [3] and L.tolist() == [5] and d[0] == pytest.approx(1.1, abs=1e-6)
    r, L, d = image_ranks(
        q, db, frame, np.array([3]), [np.array([2, 3])]
    )  # the place {2, 3}: d = 0.1, nothing outside closer
    assert r.tolist() == [1] and L.tolist() == [4] and d[0] == pytest.approx(0.1, abs=1e-6)
    r, L, d = image_ranks(
        q, db, frame, np.array([3]), [np.array([3, 4])]
    )  # place {3, 4}: d = 1.1; frames 2, 1 closer
    assert r.tolist() == [3] and L.tolist() == [4]


def test_radius_zero_reproduces_the_single_frame_rank() -> None:
    """gt_radius_m = 0.

    Places of G alone give exactly the ranks without a place (the earlier engine).
    """
    import pandas as pd

    from harness.pairs import ground_truth_places

    rng = np.random.default_rng(3)
    db = rng.normal(size=(200, 5)).astype(np.float32)
    frame = rng.integers(0, 30, 200) * 1000
    q = rng.normal(size=(20, 5)).astype(np.float32)
    gt = rng.choice(np.unique(frame), 20)
    ref = pd.DataFrame(
        {
            "utime": np.unique(frame),
            "x": np.arange(len(np.unique(frame))) * 0.5,
            "y": 0.0,
            "yaw": 0.0,
        }
    )
    places = ground_truth_places(ref, gt, 0.0, 45.0)
    r0, L0, d0 = image_ranks(q, db, frame, gt)
    r1, L1, d1 = image_ranks(q, db, frame, gt, [places[int(g)] for g in gt])
    assert np.array_equal(r0, r1) and np.array_equal(L0, L1) and np.array_equal(d0, d1)
    # frames 0.5 m apart: a 1.2 m radius holds G and two neighbours on each side (fewer at the ends)
    wide = ground_truth_places(ref, gt, 1.2, 45.0)
    assert all(len(wide[int(g)]) in (3, 4, 5) for g in gt)


def test_places_respect_the_heading_gate() -> None:
    import pandas as pd

    from harness.pairs import ground_truth_places

    ref = pd.DataFrame(
        {"utime": [1, 2, 3, 4], "x": [0.0, 0.5, 1.0, 0.2], "y": 0.0, "yaw": [0.0, 0.1, 0.0, np.pi]}
    )
    assert ground_truth_places(ref, np.array([1]), 2.0, 45.0)[1].tolist() == [
        1,
        2,
        3,
    ]  # frame 4 faces the other way


def test_d_is_exact_for_a_query_equal_to_a_database_row() -> None:
    rng = np.random.default_rng(4)
    db = rng.normal(size=(50, 4096)).astype(np.float32) * 10
    frame = np.repeat(np.arange(10), 5)
    q = db[[7, 23]].copy()
    _, _, d = image_ranks(q, db, frame, np.array([1, 4]))
    assert d.tolist() == [0.0, 0.0]


def test_ties_count_in_the_query_s_favour() -> None:
    db = np.array(
        [[1, 0], [1, 0], [0, 1], [1, 0]], np.float32
    )  # frames 1, 2, 3, 4; 1, 2, 4 identical
    frame = np.array([1, 2, 3, 4])
    q = np.array([[1, 0], [0, 1]], np.float32)
    r, L, d = image_ranks(q, db, frame, np.array([2, 1]))
    assert L.tolist() == [4, 4]
    assert r.tolist() == [
        1,
        2,
    ]  # tie with frames 1 and 4 -> rank 1; frame 3 is strictly closer for q2
    assert d[0] == 0.0


def test_missing_ground_truth_frame_is_an_error() -> None:
    with pytest.raises(RetrievalError, match="no subimage"):
        image_ranks(np.zeros((1, 2)), np.zeros((2, 2)), np.array([1, 2]), np.array([3]))


def test_faiss_is_exact_where_it_says_so() -> None:
    rng = np.random.default_rng(1)
    db = rng.normal(size=(500, 8)).astype(np.float32)
    frame = rng.integers(0, 50, 500)
    q = rng.normal(size=(40, 8)).astype(np.float32)
    gt = rng.choice(np.unique(frame), 40)
    exact, _, dist = image_ranks(q, db, frame, gt)
    res = image_ranks_faiss(q, db, frame, gt, k=64)
    assert res.exact.any()
    assert np.array_equal(res.rank[res.exact], exact[res.exact])
    assert (res.rank[~res.exact] <= exact[~res.exact]).all()  # a lower bound otherwise
    np.testing.assert_allclose(res.dist, dist, rtol=1e-4)
    full = image_ranks_faiss(q, db, frame, gt, k=500)
    assert full.exact.all() and np.array_equal(full.rank, exact)


PAIRS = pd.DataFrame(
    {
        "q_session": ["A"],
        "q_camera": ["c"],
        "q_utime": [1],
        "r_session": ["B"],
        "r_camera": ["c"],
        "r_utime": [30],
        "season_pair": ["WI->SU"],
    }
)


def _imp(ranked: list, L: int, **kw: object) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "q_session": ["A"],
            "q_camera": ["c"],
            "q_utime": [1],
            "method": ["grid5"],
            "box_id": [0],
            "x1": [0.0],
            "y1": [0.0],
            "x2": [5.0],
            "y2": [5.0],
            "r_session": ["B"],
            "ranked": [ranked],
            "L": [L],
            **{k: [v] for k, v in kw.items()},
        }
    )


def test_imported_lists() -> None:
    df, counts = ranks_from_import(_imp([10, 30, 20], 50, distance=0.7), PAIRS, "x")
    assert df["rank"][0] == 2 and df["r"][0] == 2 / 50 and df["d"][0] == 0.7 and df["exact"][0]
    df, counts = ranks_from_import(_imp([10, 20], 50), PAIRS, "x")
    assert (
        df["rank"][0] == 50 and not df["exact"][0] and counts["gt_missing_from_truncated_list"] == 1
    )
    df, _ = ranks_from_import(_imp([10, 20], 50), PAIRS, "x", missing="next")
    assert df["rank"][0] == 3
    with pytest.raises(RetrievalError, match="missing from a complete list"):
        ranks_from_import(_imp([10, 20], 2), PAIRS, "x")
    with pytest.raises(RetrievalError, match="repeats a frame"):
        ranks_from_import(_imp([10, 10, 30], 9), PAIRS, "x")


REF_FRAMES = pd.DataFrame(
    {
        "session": "B",
        "camera": "c",
        "utime": [10, 20, 30, 40, 50],
        "x": [0.0, 5.0, 10.0, 11.0, 20.0],
        "y": 0.0,
        "yaw": 0.0,
    }
)


def test_imported_lists_are_scored_against_the_place() -> None:
    # G = 30 at x = 10; frame 40 at x = 11 belongs to its place (radius 2 m), the others do not
    df, _ = ranks_from_import(
        _imp([10, 40, 30, 20, 50], 5, distance=0.7), PAIRS, "x", REF_FRAMES, gt_radius_m=2.0
    )
    assert (
        df["rank"][0] == 2 and df["L"][0] == 4 and df["place_size"][0] == 2
    )  # 10 listed before 40; L = 1 + 3 outside
    assert df["r"][0] == pytest.approx(2 / 4) and df["r_desc"][0] == pytest.approx(3 / 4)
    df, _ = ranks_from_import(
        _imp([10, 40, 30, 20, 50], 5), PAIRS, "x", REF_FRAMES, gt_radius_m=0.0
    )
    assert df["rank"][0] == 3 and df["L"][0] == 5  # the single frame: 10 and 40 before it
    # truncated list without the place: 'next' counts only listed frames outside it
    df, counts = ranks_from_import(
        _imp([10, 20], 5), PAIRS, "x", REF_FRAMES, gt_radius_m=2.0, missing="next"
    )
    assert (
        df["rank"][0] == 3 and not df["exact"][0] and counts["gt_missing_from_truncated_list"] == 1
    )


def test_imported_ids_that_match_no_frame_are_refused_or_counted() -> None:
    # nanoseconds for microseconds: no id matches a frame of session B
    with pytest.raises(
        RetrievalError,
        match=r"5 of 5 listed reference ids match no frame.*e\.g\. 10000 in session B",
    ):
        ranks_from_import(_imp([10000, 20000, 30000, 40000, 50000], 5), PAIRS, "x", REF_FRAMES)
    df, counts = ranks_from_import(
        _imp([10, 20, 30, 99], 5), PAIRS, "x", REF_FRAMES
    )  # one stray id: counted
    assert counts["unmatched_reference_ids"] == 1 and df["rank"][0] == 3


def test_a_memory_budget_ranks_in_groups_with_the_same_result() -> None:
    """``memory_mb`` bounds the (queries x frames) matrices.

    Tiny budgets give groups of one query.
    """
    rng = np.random.default_rng(3)
    db = rng.standard_normal((600, 8)).astype(np.float16)
    frame = np.repeat(np.arange(150), 4)
    q = rng.standard_normal((37, 8)).astype(np.float32)
    gt = rng.choice(150, 37)
    place = [np.array([g, (g + 1) % 150]) for g in gt]
    whole = image_ranks(q, db, frame, gt, place, chunk_rows=64)
    for mb in (1e-6, 150 * 16 * 5 / 2**20):  # one query per group; five per group
        got = image_ranks(q, db, frame, gt, place, chunk_rows=64, memory_mb=mb)
        for a, b in zip(whole, got, strict=True):
            np.testing.assert_array_equal(a, b)

"""Image-level ranks against a brute-force loop; the faiss engine; imported rank lists."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from harness.errors import RetrievalError
from harness.ranks_import import ranks_from_import
from harness.retrieval import image_ranks, image_ranks_faiss


def brute(q: np.ndarray, db: np.ndarray, frame: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    frames = np.unique(frame)
    rank, dist = [], []
    for qi, g in zip(q, gt, strict=True):
        fm = {f: np.sqrt(((db[frame == f] - qi) ** 2).sum(1)).min() for f in frames}
        rank.append(1 + sum(1 for f in frames if f != g and fm[f] < fm[g]))
        dist.append(fm[g])
    return np.array(rank), len(frames), np.array(dist)


@pytest.mark.parametrize(("chunk", "batch"), [(8192, 1024), (7, 3), (1, 1)])
def test_matches_brute_force_with_several_subimages_per_frame(chunk: int, batch: int) -> None:
    rng = np.random.default_rng(0)
    db = rng.normal(size=(300, 6)).astype(np.float32)
    frame = rng.integers(100, 140, 300)
    q = rng.normal(size=(25, 6)).astype(np.float32)
    gt = rng.choice(np.unique(frame), 25)
    r, L, d = image_ranks(q, db, frame, gt, chunk_rows=chunk, query_batch=batch)
    br, bl, bd = brute(q, db, frame, gt)
    assert bl == L and np.array_equal(r, br)
    np.testing.assert_allclose(d, bd, rtol=1e-4, atol=1e-4)


def test_ties_count_in_the_query_s_favour() -> None:
    db = np.array([[1, 0], [1, 0], [0, 1], [1, 0]], np.float32)  # frames 1, 2, 3, 4; 1, 2, 4 identical
    frame = np.array([1, 2, 3, 4])
    q = np.array([[1, 0], [0, 1]], np.float32)
    r, L, d = image_ranks(q, db, frame, np.array([2, 1]))
    assert L == 4
    assert r.tolist() == [1, 2]  # tie with frames 1 and 4 -> rank 1; frame 3 is strictly closer for q2
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


PAIRS = pd.DataFrame({"q_session": ["A"], "q_camera": ["c"], "q_utime": [1], "r_session": ["B"], "r_camera": ["c"], "r_utime": [30], "season_pair": ["WI->SU"]})


def _imp(ranked: list, L: int, **kw: object) -> pd.DataFrame:
    return pd.DataFrame({"q_session": ["A"], "q_camera": ["c"], "q_utime": [1], "method": ["grid5"], "box_id": [0], "x1": [0.0], "y1": [0.0],
                         "x2": [5.0], "y2": [5.0], "r_session": ["B"], "ranked": [ranked], "L": [L], **{k: [v] for k, v in kw.items()}})


def test_imported_lists() -> None:
    df, counts = ranks_from_import(_imp([10, 30, 20], 50, distance=0.7), PAIRS, "x")
    assert df["rank"][0] == 2 and df["r"][0] == 2 / 50 and df["d"][0] == 0.7 and df["exact"][0]
    df, counts = ranks_from_import(_imp([10, 20], 50), PAIRS, "x")
    assert df["rank"][0] == 50 and not df["exact"][0] and counts["gt_missing_from_truncated_list"] == 1
    df, _ = ranks_from_import(_imp([10, 20], 50), PAIRS, "x", missing="next")
    assert df["rank"][0] == 3
    with pytest.raises(RetrievalError, match="missing from a complete list"):
        ranks_from_import(_imp([10, 20], 2), PAIRS, "x")
    with pytest.raises(RetrievalError, match="repeats a frame"):
        ranks_from_import(_imp([10, 10, 30], 9), PAIRS, "x")

"""Image-level ranks against a brute-force loop; the faiss engine; imported rank lists."""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest
import torch

from harness.errors import RetrievalError
from harness.retrieval import Engine, FaissSearch, image_ranks, image_ranks_faiss


def brute(
    q: np.ndarray, db: np.ndarray, frame: np.ndarray, gt: np.ndarray, place: list | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """method §6 as a loop.

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
    r, L, d = image_ranks(q, db, frame, gt, engine=Engine(chunk_rows=chunk, query_batch=batch))
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
    r, L, d = image_ranks(
        q, db, frame, gt, place, engine=Engine(chunk_rows=chunk, query_batch=batch)
    )
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

    from harness.retrieval.places import ground_truth_places

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

    from harness.retrieval.places import ground_truth_places

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
    res = image_ranks_faiss(q, db, frame, gt, search=FaissSearch(k=64))
    assert res.exact.any()
    assert np.array_equal(res.rank[res.exact], exact[res.exact])
    assert (res.rank[~res.exact] <= exact[~res.exact]).all()  # a lower bound otherwise
    np.testing.assert_allclose(res.dist, dist, rtol=1e-4)
    full = image_ranks_faiss(q, db, frame, gt, search=FaissSearch(k=500))
    assert full.exact.all() and np.array_equal(full.rank, exact)


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
    whole = image_ranks(q, db, frame, gt, place, engine=Engine(chunk_rows=64))
    for mb in (1e-6, 150 * 16 * 5 / 2**20):  # one query per group; five per group
        got = image_ranks(q, db, frame, gt, place, engine=Engine(chunk_rows=64, memory_mb=mb))
        for a, b in zip(whole, got, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("lengths", [[5, 5, 5, 5], [1, 12, 3, 7, 2], [4]])
def test_the_per_frame_minimum_equals_a_loop_over_frames(lengths: list[int]) -> None:
    from harness.retrieval import frame_min_sqdist_chunk

    rng = np.random.default_rng(len(lengths))
    q = torch.from_numpy(rng.standard_normal((9, 6)).astype(np.float32))
    block = torch.from_numpy(rng.standard_normal((sum(lengths), 6)).astype(np.float32))
    got = frame_min_sqdist_chunk(
        q, q.square().sum(1, keepdim=True), block, torch.tensor(lengths)
    ).numpy()
    d2 = ((q.numpy()[:, None, :] - block.numpy()[None]) ** 2).sum(-1)
    cuts = np.cumsum([0, *lengths])
    want = np.stack([d2[:, a:b].min(1) for a, b in itertools.pairwise(cuts)], 1)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def _exact_d(q: np.ndarray, db: np.ndarray, frame: np.ndarray, members: list) -> np.ndarray:
    """method §6's d: float64 differences, numpy's sum of each row, the least over the place."""
    return np.array(
        [
            np.sqrt(((db[np.isin(frame, m)].astype(np.float64) - qi) ** 2).sum(1).min())
            for qi, m in zip(q, members, strict=True)
        ]
    )


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_d_is_bit_for_bit_the_float64_difference_with_near_ties(dtype: type) -> None:
    """Places of 3 frames x 8 rows, all near one another: many rows within the product's error.

    The rows the engine leaves unmeasured cannot hold the minimum (its error bound), so ``d``
    is the same float64 value as measuring every row of the place, across chunk and batch cuts.
    """
    rng = np.random.default_rng(11)
    dim, frames = 3000, 30
    base = rng.standard_normal((frames // 3, dim)).astype(np.float32)
    db = (np.repeat(base, 24, 0) + 1e-3 * rng.standard_normal((frames * 8, dim))).astype(dtype)
    frame = np.repeat(np.arange(frames), 8)
    gt = rng.choice(frames, 40)
    q = (base[gt // 3] + 1e-3 * rng.standard_normal((40, dim))).astype(np.float32)
    place = [np.array([3 * (g // 3), 3 * (g // 3) + 1, 3 * (g // 3) + 2]) for g in gt]
    want = _exact_d(q, db, frame, place)
    for chunk, batch in ((8192, 1024), (20, 7)):
        _, _, d = image_ranks(
            q, db, frame, gt, place, engine=Engine(chunk_rows=chunk, query_batch=batch)
        )
        np.testing.assert_array_equal(d, want)


def test_d_is_exact_where_the_product_s_error_exceeds_the_distances() -> None:
    """Descriptors of norm ~6,000 that differ by ~1: the float32 expansion is off by more than the
    distances between a place's rows, so its best row is often not the nearest. The error bound
    then grows with the norms and every such row is measured (a fixed tolerance of 0.01 + 0.1%
    of the best value, the rule before, missed the nearest row here)."""
    rng = np.random.default_rng(5)
    dim = 4096
    base = 100 * rng.standard_normal((6, dim)).astype(np.float32)
    db = np.repeat(base, 16, 0) + 0.01 * rng.standard_normal((96, dim)).astype(np.float32)
    frame = np.repeat(np.arange(6), 16)
    gt = rng.choice(6, 30)
    q = base[gt] + 0.01 * rng.standard_normal((30, dim)).astype(np.float32)
    _, _, d = image_ranks(q, db, frame, gt)
    np.testing.assert_array_equal(d, _exact_d(q, db, frame, [[g] for g in gt]))


def test_the_expansion_error_bound_holds_and_prunes() -> None:
    """``expansion_error_factor``: every fast value lies within its bound; the bound grows with a
    product that may round its inputs (TF32), and is infinite where it would say nothing."""
    from harness.retrieval.distances import expansion_error_factor
    from harness.retrieval.exact import ExactPlace

    rng = np.random.default_rng(8)
    dim = 2048
    for scale in (1.0, 1e3):
        q = torch.from_numpy(scale * rng.standard_normal((64, dim)).astype(np.float32))
        noise = scale * 1e-3 * rng.standard_normal((32, dim))
        b = torch.from_numpy((q[:32].numpy() + noise).astype(np.float16).astype(np.float32))
        qn = torch.linalg.vector_norm(q, dim=1, keepdim=True).square_()
        bn = torch.linalg.vector_norm(b, dim=1).square_()
        v = (qn + bn[None]).addmm_(q, b.T, alpha=-2.0).clamp_min_(0).double().numpy()
        exact = ((q.double()[:, None] - b.double()[None]) ** 2).sum(-1).numpy()
        bound = (
            expansion_error_factor(dim)
            * (np.sqrt(qn.double().numpy()) + np.sqrt(bn.double().numpy())[None]) ** 2
        )
        assert (np.abs(v - exact) <= bound).all()
    assert expansion_error_factor(2**23) == float("inf")
    before, full = torch.get_float32_matmul_precision(), expansion_error_factor(dim)
    try:
        torch.set_float32_matmul_precision("high")  # TF32 inputs: 10-bit fractions
        assert expansion_error_factor(dim) >= full + 2 * 2.0**-11
    finally:
        torch.set_float32_matmul_precision(before)
    # unit vectors in 16,384 dimensions: a few rows per query measured, not the place's 16
    q = rng.standard_normal((256, 16384)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    db = rng.standard_normal((16 * 20, 16384)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    frame = np.repeat(np.arange(20), 16)
    gt = rng.choice(20, 256)
    made: list = []
    real_init = ExactPlace.__init__

    def spy(self: ExactPlace, *a: object) -> None:
        real_init(self, *a)  # type: ignore[arg-type]
        made.append(self)

    ExactPlace.__init__ = spy  # type: ignore[method-assign]
    try:
        _, _, d = image_ranks(q, db.astype(np.float16), frame, gt)
    finally:
        ExactPlace.__init__ = real_init  # type: ignore[method-assign]
    assert 256 <= made[0].measured < 256 * 4
    np.testing.assert_array_equal(d, _exact_d(q, db.astype(np.float16), frame, [[g] for g in gt]))


def test_the_exact_step_reads_database_rows_as_a_device_pass_does() -> None:
    """A CUDA pass measures its pairs from the host arrays (float16 rows, database order): the
    same values as from a chunk's float32 rows."""
    from harness.retrieval.distances import expansion_error_factor
    from harness.retrieval.exact import ExactPlace

    rng = np.random.default_rng(9)
    db = rng.standard_normal((40, 500)).astype(np.float16)
    q = rng.standard_normal((6, 500)).astype(np.float32)
    order = rng.permutation(40)
    ii = np.repeat(np.arange(6), 5)
    rows = rng.integers(0, 40, 30)
    v = np.zeros(30, np.float32)  # no pruning: every pair within every bound
    bn = np.full(30, 1e9)
    f = expansion_error_factor(500)
    host, chunk = ExactPlace(np.ones(6), f), ExactPlace(np.ones(6), f)
    host.add(ii, v, bn, q, db, order[rows])
    block = db[order].astype(np.float32)
    chunk.add(ii, v, bn, q, block, np.argsort(order)[order[rows]])
    np.testing.assert_array_equal(host.best, chunk.best)
    want = [
        ((db[order[rows[ii == k]]].astype(np.float64) - q[k]) ** 2).sum(1).min() for k in range(6)
    ]
    np.testing.assert_array_equal(host.best, want)


@pytest.mark.parametrize(
    ("dim", "scale", "offset"), [(8, 1.0, 0.0), (128, 30.0, 0.0), (256, 1e-3, 0.0), (64, 1.0, 40.0)]
)
def test_bf16_candidates_give_exact_ranks_and_d(dim: int, scale: float, offset: float) -> None:
    """``precision = "bf16"``: random descriptors of several norms (rows of one call from 0.2 to
    3 times ``scale``): ranks, L and d identical to the brute-force loop and, near the origin, to
    fp32's, in any chunking; some frames were left to the exact measurement, most were not. Far
    from the origin (offset 40 in every dimension) fp32's fast comparisons miss some ranks; the
    bf16 path, centred and decided exactly, does not."""
    rng = np.random.default_rng(dim)
    m, n = 1200, 90
    db = rng.standard_normal((m, dim)) * rng.uniform(0.2, 3, (m, 1)) * scale + offset
    db = db.astype(np.float16 if scale == 1.0 else np.float32)  # float16 rows too
    frame = rng.integers(0, 150, m)
    q = (db[rng.integers(0, m, n)] + rng.standard_normal((n, dim)) * 0.4 * scale).astype(np.float32)
    gt = frame[rng.integers(0, m, n)]
    place = [np.array([int(g), int(g) + 1]) for g in gt]
    want = brute(q, db, frame, gt, place)
    stats: dict[str, int] = {}
    for chunk, batch in [(8192, 1024), (97, 7)]:
        bf = image_ranks(
            q,
            db,
            frame,
            gt,
            place,
            stats=stats,
            engine=Engine(chunk_rows=chunk, query_batch=batch, precision="bf16"),
        )
        for a, b in zip(want, bf, strict=True):
            np.testing.assert_array_equal(a, b)
        fp = image_ranks(
            q, db, frame, gt, place, engine=Engine(chunk_rows=chunk, query_batch=batch)
        )
        np.testing.assert_array_equal(fp[1], bf[1])
        np.testing.assert_array_equal(fp[2], bf[2])
        assert np.array_equal(fp[0], bf[0]) == (offset == 0)
    assert stats["compared"] == 2 * int((bf[1] - 1).sum())
    assert 0 < stats["measured_exactly"] < stats["compared"] / 2


def test_the_bf16_bound_holds_for_the_product_torch_computes() -> None:
    """:func:`bf16_error_factor` against the values the engine's bf16 path computes (centred,
    bfloat16 product, float32 norms), measured pair by pair: never beyond the bound."""
    from harness.retrieval.distances import bf16_error_factor, sqdist_into

    rng = np.random.default_rng(5)
    for dim, scale in [(16, 1.0), (512, 100.0), (2048, 1e-2)]:
        q = (rng.standard_normal((40, dim)) * scale + scale).astype(np.float32)
        b = (rng.standard_normal((300, dim)) * rng.uniform(0.1, 4, (300, 1)) * scale).astype(
            np.float32
        )
        c = q.mean(0, dtype=np.float64).astype(np.float32)
        qc, bc = (
            torch.from_numpy(q) - torch.from_numpy(c),
            torch.from_numpy(b) - torch.from_numpy(c),
        )
        qn = torch.linalg.vector_norm(qc, dim=1, keepdim=True).square_()
        bn = torch.linalg.vector_norm(bc, dim=1).square_()
        out = torch.empty((40, 300))
        v = sqdist_into(qc.bfloat16(), qn, bc.bfloat16(), bn, out).double().numpy()
        true = ((q[:, None, :].astype(np.float64) - b[None].astype(np.float64)) ** 2).sum(2)
        bound = (
            bf16_error_factor(dim)
            * (np.sqrt(qn.double().numpy()) + np.sqrt(bn.double().numpy())[None]) ** 2
        )
        assert (np.abs(v - true) <= bound).all()
        assert np.abs(v - true).max() > 1e-3 * bound.max()  # bf16 arithmetic was used


def test_bf16_ties_count_in_the_querys_favour() -> None:
    """A frame outside the place with the same rows as the place's is as close, not closer: the
    bf16 path measures it exactly and does not count it (rank 1), as the loop says."""
    rng = np.random.default_rng(1)
    rows = rng.standard_normal((4, 32)).astype(np.float32)
    db = np.concatenate([rows, rows, rng.standard_normal((40, 32)).astype(np.float32) + 3])
    frame = np.repeat(np.arange(12), 4)
    q = rows[:1] + np.float32(0.01)
    stats: dict[str, int] = {}
    r, L, _ = image_ranks(q, db, frame, np.array([0]), stats=stats, engine=Engine(precision="bf16"))
    br, bl, _ = brute(q, db, frame, np.array([0]))
    assert r.tolist() == br.tolist() == [1] and L.tolist() == bl.tolist() == [12]
    assert stats["measured_exactly"] >= 1  # frame 1 could not be decided by the bound


def test_an_unknown_rank_precision_is_an_error() -> None:
    with pytest.raises(RetrievalError, match="precision"):
        image_ranks(
            np.zeros((1, 2)),
            np.zeros((2, 2)),
            np.array([1, 2]),
            np.array([1]),
            engine=Engine(precision="fp16"),
        )

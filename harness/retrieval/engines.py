"""Image-level rank engines (method §6).

For a query subimage q whose ground-truth reference frame is G, with the ground-truth *place*
P(G) (the reference frames near G; P(G) = {G} when no place is given):
``dist(q, F)`` is the smallest L2 distance from q to any subimage of frame F;
``d(q) = min over F in P(G) of dist(q, F)``, computed exactly (differences, not the expansion);
``rank(q) = 1 + #{F outside P(G) : dist(q, F) < d(q)}`` (ties counted in q's favour);
``L = 1 + #frames outside P(G)``; ``r = rank / L``; ``r' = (L + 1 - rank) / L``.

The exact engine computes the per-frame minimum with batched matrix products over chunks of the
database, so memory is bounded by ``query_batch x (chunk_rows + L)`` whatever the database size;
on CPU a chunk holds at most :data:`CPU_CHUNK_BYTES` of float32 rows, in buffers kept between
calls by the calling thread (:func:`workspace`).
An optional faiss engine returns the same quantities from a top-k search (exact for every query
whose ground-truth frame is found among the top k; otherwise a lower bound, flagged).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from harness.errors import RetrievalError
from harness.retrieval.distances import (
    bf16_error_factor,
    expansion_error_factor,
    frame_min,
    pad_index,
    sqdist_into,
    workspace,
)
from harness.retrieval.exact import ExactPlace, FrameMeasure, exact_ranks
from harness.retrieval.layout import frame_layout, place_columns

log = logging.getLogger(__name__)

#: Bytes per (query, frame) cell a group holds at its peak: the float32 minima, the place mask, the
#: masked copy and the comparison's boolean temporaries.
CELL_BYTES = 16
# : Database rows per chunk on a CUDA device (at least): larger than on CPU, where a chunk should
# stay in cache.
CUDA_CHUNK_ROWS = 65536
#: Bytes of one chunk's float32 rows on CPU (at most): 512 rows at D = 16,384. MKL's product
#: runs at its best rate with a few hundred database rows per call (``python -m bench --only
#: ranking``; 1,000 or more rows per call measured up to a quarter slower on this project's
#: machines), and the buffer is small enough to keep between calls (:func:`workspace`).
CPU_CHUNK_BYTES = 32 * 2**20
#: The candidate product's arithmetic: float32 (ranks from its minima), or bfloat16 (the frames
#: its error bound cannot decide measured exactly: :func:`exact_ranks`).
RANK_PRECISIONS = ("fp32", "bf16")


def _chunks(starts: np.ndarray, m: int, chunk_rows: int) -> list[tuple[int, int]]:
    """(first frame, end frame) ranges of about ``chunk_rows`` rows, cut at frame boundaries."""
    bounds = np.concatenate([starts, [m]])
    out, f0, L = [], 0, len(starts)
    while f0 < L:
        f1 = int(np.searchsorted(bounds, bounds[f0] + chunk_rows, side="right")) - 1
        f1 = min(max(f1, f0 + 1), L)
        out.append((f0, f1))
        f0 = f1
    return out


@dataclass(frozen=True)
class Engine:
    """How :func:`image_ranks` streams the database and multiplies.

    ``chunk_rows``: database rows per streamed chunk; ``query_batch``: queries per matrix
    product; ``device``: ``"cpu"`` or ``"cuda"`` (float32 products; float16 rows converted on the
    device); ``memory_mb``: the budget (MiB) of the per-group (queries x frames) matrices,
    :data:`CELL_BYTES` per cell; ``precision``: the candidate product, ``fp32``, or ``bf16``
    (centred vectors, a bfloat16 product: its bound, :func:`bf16_error_factor`, leaves frames to
    measure exactly).
    """

    chunk_rows: int = 8192
    query_batch: int = 1024
    device: str | torch.device = "cpu"
    memory_mb: float = 1024.0
    precision: str = "fp32"


def image_ranks(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    gt_frame: np.ndarray,
    place: Sequence[np.ndarray] | None = None,
    engine: Engine = Engine(),
    stats: dict[str, int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact image-level ranks of the ground-truth places.

    The database is streamed in chunks of about ``chunk_rows`` rows (cut at frame boundaries), each
    read once and converted to float32 on the fly, so ``db_desc`` may be a float16 memmap of any
    size. Memory is bounded by ``memory_mb``, not by the data: queries are ranked in groups
    whose (group, frames) per-frame minimum and place mask fit in it (each group streams the
    database once), plus one chunk of ``chunk_rows`` rows (on CPU at most
    :data:`CPU_CHUNK_BYTES`) and its (query_batch x chunk_rows) distances. ``d`` is computed
    exactly from the place's own rows (differences, float64), so a query equal to a database
    row gets ``d = 0``. In fp32, ranks compare the float32 product's per-frame minima with each
    other. In bf16 a frame counts when its minimum is below ``d`` by more than the product's
    error bound and is measured exactly where the bound cannot decide (:func:`exact_ranks`):
    exact ranks, ties in the query's favour. fp32's equal them except where a frame lies within
    float32's rounding of ``d`` (or descriptors lie far from the origin). fp32 does not decide
    that way: its worst-case bound grows with ``D`` (16,384-D: most frames undecided, 18x slower).

    Args:
        query_desc: (n, D) query subimage descriptors.
        db_desc: (m, D) database subimage descriptors (array or memmap).
        db_frame: (m,) integer frame id of each database row.
        gt_frame: (n,) ground-truth frame id of each query (must occur in ``db_frame``).
        place: per query, the frame ids of its ground-truth place P(G) (G is always added; ids
            with no database row are ignored). None: P(G) = {G}, the literal single-frame rank.
        engine: how the database is streamed and multiplied (:class:`Engine`).
        stats: Where given, counts are added to it: ``compared`` (query x frame comparisons) and
            ``measured_exactly`` (those the bound left to the exact measurement).

    Returns:
        ``rank`` (n,) int64, ``L`` (n,) int64 (1 + frames outside the place), ``dist`` (n,)
        float64 exact L2 distance ``d`` to the place.

    Raises:
        RetrievalError: shapes disagree or a ground-truth frame has no database row.
    """
    db_frame = np.asarray(db_frame)
    gt_frame = np.asarray(gt_frame)
    _check_inputs(query_desc, db_desc, db_frame, gt_frame, engine.precision)
    order, frame_ids, starts = frame_layout(db_frame)
    L = len(frame_ids)
    pcols = place_columns(frame_ids, gt_frame, place)
    n = len(query_desc)
    group = max(1, int(engine.memory_mb * 2**20 // (CELL_BYTES * max(L, 1))))
    rows = _chunk_rows(engine.chunk_rows, torch.device(engine.device), db_desc.shape[1])
    run = dataclasses.replace(engine, chunk_rows=rows)
    rank, Lq, dist = (np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.float64))
    for g0 in range(0, n, group):
        g = slice(g0, min(n, g0 + group))
        rank[g], Lq[g], dist[g] = _rank_group(
            query_desc[g],
            db_desc,
            (order, starts),
            pcols[g],
            run,
            stats if stats is not None else {},
        )
    return rank, Lq, dist


def _check_inputs(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    gt_frame: np.ndarray,
    precision: str,
) -> None:
    """:func:`image_ranks`'s arguments agree with each other (else :class:`RetrievalError`)."""
    if query_desc.ndim != 2 or db_desc.ndim != 2 or query_desc.shape[1] != db_desc.shape[1]:
        raise RetrievalError(
            f"descriptor shapes disagree: query {query_desc.shape}, database {db_desc.shape}"
        )
    if len(db_frame) != len(db_desc) or len(gt_frame) != len(query_desc):
        raise RetrievalError("db_frame must align with db_desc and gt_frame with query_desc")
    if precision not in RANK_PRECISIONS:
        raise RetrievalError(f"precision must be one of {RANK_PRECISIONS}, got {precision!r}")


def _chunk_rows(chunk_rows: int, device: torch.device, dim: int) -> int:
    """Database rows per streamed chunk on ``device``.

    On CUDA at least :data:`CUDA_CHUNK_ROWS` (device memory is large and the copy costs more
    than the product); on CPU at most :data:`CPU_CHUNK_BYTES` of float32 rows (a chunk's rows
    are first touched once per call: keep them a few megabytes).
    """
    if device.type == "cuda":
        return max(chunk_rows, CUDA_CHUNK_ROWS)
    return max(1, min(chunk_rows, CPU_CHUNK_BYTES // (4 * max(dim, 1))))


def _place_rows(
    pair_q: np.ndarray, pair_c: np.ndarray, bounds: np.ndarray, f0: int, f1: int
) -> tuple[np.ndarray, np.ndarray]:
    """(query, chunk-local row) of every row of a place frame in the chunk of frames f0..f1.

    ``pair_q``, ``pair_c``: the (query, place frame) pairs in frame order; one run of rows per
    pair.
    """
    a, b = np.searchsorted(pair_c, [f0, f1])
    cq, cc = pair_q[a:b], pair_c[a:b]
    clen = bounds[cc + 1] - bounds[cc]
    rep = np.repeat(np.arange(len(cc)), clen)
    first = np.concatenate([[0], np.cumsum(clen)[:-1]]).astype(np.int64)
    crow = (bounds[cc] - bounds[f0])[rep] + np.arange(len(rep)) - first[rep]
    return cq[rep], crow


def _place_ranks(fm: torch.Tensor, qi: np.ndarray, pc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rank of each query's place and its L from the (queries x frames) per-frame minima ``fm``.

    ``qi``, ``pc``: the (query, place frame) pairs. Frames of the place never count: ``d`` is
    their smallest minimum, so none of them lies below it, and one comparison of the whole matrix
    counts the frames outside it that do. The place's columns are read through the pairs, not
    through a (queries x frames) mask: two passes over the matrix instead of seven (4x faster at
    4,096 x 12,500, the same integers).
    """
    n, L = fm.shape
    dev = fm.device
    q = torch.from_numpy(qi).to(dev)
    dg = torch.full((n,), float("inf"), dtype=fm.dtype, device=dev)
    dg.scatter_reduce_(0, q, fm[q, torch.from_numpy(pc).to(dev)], "amin")
    rank = (fm < dg[:, None]).sum(1, dtype=torch.int32).cpu().numpy().astype(np.int64) + 1
    cells = np.unique(qi.astype(np.int64) * L + pc)  # a place frame named twice counts once
    Lq = L + 1 - np.bincount(cells // max(L, 1), minlength=n).astype(np.int64)
    return rank, Lq


def _rank_group(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    layout: tuple[np.ndarray, np.ndarray],
    pcols: list[np.ndarray],
    engine: Engine,
    stats: dict[str, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`image_ranks` for one group of queries: one pass over the database.

    The pass writes into buffers allocated once (a chunk's float32 rows, one batch's distances):
    a fresh multi-megabyte tensor per chunk costs its page faults, as much as the float16
    conversion itself. While a chunk's rows and distances are at hand, the rows of each query's
    place that may hold its exact ``d`` are measured (:class:`ExactPlace`): no second pass.
    ``layout``: the database rows in frame order and each frame's first (:func:`frame_layout`);
    ``engine``: its chunk rows fitted to the device (:func:`_chunk_rows`). In ``bf16`` the
    products are in bfloat16 of vectors centred on the group's mean query (smaller norms, a
    tighter bound), each frame's largest centred row norm kept for the bound.
    """
    (order, starts), dev, bf16 = layout, torch.device(engine.device), engine.precision == "bf16"
    chunk_rows, query_batch = engine.chunk_rows, engine.query_batch
    L, n = len(starts), len(query_desc)
    contiguous = bool(np.all(order == np.arange(len(order))))
    bounds = np.concatenate([starts, [len(order)]])
    lhs, qnorms, center = _query_batches(query_desc, query_batch, dev, bf16)
    qi = np.repeat(np.arange(n), [len(c) for c in pcols])
    pc = np.concatenate(pcols) if n else np.zeros(0, np.int64)
    by_col = np.argsort(pc, kind="stable")
    pair_q, pair_c = qi[by_col], pc[by_col]  # (query, place column) pairs in column order
    chunks = _chunks(starts, len(order), chunk_rows)
    widest = max((int(bounds[f1] - bounds[f0]) for f0, f1 in chunks), default=0)
    direct = db_desc.dtype == np.float32 and dev.type == "cpu"
    block_buf = None if direct else workspace("block", widest * db_desc.shape[1], dev)
    d2_buf = workspace("d2", min(query_batch, max(n, 1)) * widest, dev)
    fm = torch.empty((n, L), dtype=torch.float32, device=dev)
    fmax = np.zeros(L)  # each frame's largest row norm (the bf16 bound)
    exact = ExactPlace(
        torch.cat(qnorms)[:, 0].double().cpu().numpy() if n else np.zeros(0),
        bf16_error_factor(db_desc.shape[1]) if bf16 else expansion_error_factor(db_desc.shape[1]),
    )
    for f0, f1 in chunks:
        r0, r1 = int(bounds[f0]), int(bounds[f1])
        block = _chunk_block(db_desc, order[r0:r1], contiguous, r0, r1, block_buf)
        rhs = block if center is None else block - center
        bn = torch.linalg.vector_norm(rhs, dim=1).square_()  # fused: no (rows x D) temporary
        bn_host = bn.double().cpu().numpy()
        if bf16:
            fmax[f0:f1] = np.maximum.reduceat(np.sqrt(bn_host), bounds[f0:f1] - r0)
        rhs = rhs.bfloat16() if bf16 else rhs
        lens = np.diff(bounds[f0 : f1 + 1]).astype(np.int64)
        idx = pad_index(lens, dev)
        cqr, crow = _place_rows(pair_q, pair_c, bounds, f0, f1)
        vals = np.empty(len(cqr), np.float32)  # fast values of those rows, batch by batch
        for bi, (q, qn) in enumerate(zip(lhs, qnorms, strict=True)):
            q0 = bi * query_batch
            # unclamped: the minima and the place's values are clamped at 0 instead
            d2 = sqdist_into(q, qn, rhs, bn, d2_buf[: len(q) * (r1 - r0)].view(len(q), -1), False)
            fm[q0 : q0 + len(q), f0:f1] = frame_min(d2, lens, idx).clamp_min_(0)
            mine = np.nonzero((cqr >= q0) & (cqr < q0 + len(q)))[0]
            if len(mine):
                sel = (
                    torch.from_numpy(cqr[mine] - q0).to(dev),
                    torch.from_numpy(crow[mine]).to(dev),
                )
                vals[mine] = d2[sel].clamp_min_(0).cpu().numpy()
        # Once per chunk, not per batch: the exact step's threads run while torch's OpenMP threads
        # spin after their last product (measured: a few milliseconds each time).
        if dev.type == "cpu":  # the chunk's rows, in memory and float32 already
            exact.add(cqr, vals, bn_host[crow], query_desc, block.numpy(), crow)
        else:  # the device's copy is not read back: the rows are read from the database
            exact.add(cqr, vals, bn_host[crow], query_desc, db_desc, order[r0 + crow])
    if not bf16:  # fp32: the fast minima compared with each other (see :func:`image_ranks`)
        rank, Lq = _place_ranks(fm, qi, pc)
    else:
        measure = FrameMeasure(query_desc, db_desc, order, bounds)
        rank, Lq = exact_ranks(fm, qi, pc, exact, fmax, measure, stats)
    return rank, Lq, np.sqrt(exact.best)


def _query_batches(
    query_desc: np.ndarray, query_batch: int, dev: torch.device, bf16: bool
) -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor | None]:
    """The group's queries in batches of ``query_batch`` on ``dev``.

    Returns (the product's left operands, their squared norms, the centre subtracted or None).
    bf16: both sides less the group's mean query (distances are unchanged, norms smaller), the
    operands in bfloat16 and the norms of the centred float32 vectors.
    """
    n = len(query_desc)
    queries = [
        torch.from_numpy(
            np.ascontiguousarray(query_desc[s : s + query_batch], dtype=np.float32)
        ).to(dev)
        for s in range(0, n, query_batch)
    ]
    center = None
    if bf16 and n:
        mean = np.mean(query_desc, axis=0, dtype=np.float64).astype(np.float32)
        center = torch.from_numpy(mean).to(dev)
        queries = [q - center for q in queries]
    qnorms = [torch.linalg.vector_norm(q, dim=1, keepdim=True).square_() for q in queries]
    return ([q.bfloat16() for q in queries] if bf16 else queries), qnorms, center


def _chunk_block(
    db_desc: np.ndarray,
    rows_order: np.ndarray,
    contiguous: bool,
    r0: int,
    r1: int,
    block_buf: torch.Tensor | None,
) -> torch.Tensor:
    """Database rows ``r0:r1`` (in frame order) as float32: the array itself or the buffer."""
    rows = np.ascontiguousarray(db_desc[r0:r1] if contiguous else db_desc[rows_order])
    with warnings.catch_warnings():  # a read-only memmap view; the tensor is only read
        warnings.simplefilter("ignore", UserWarning)
        src = torch.from_numpy(rows)
    if block_buf is None:
        return src
    # float16 -> float32 in torch (multi-threaded), into the reused buffer
    return block_buf[: src.numel()].view(src.shape).copy_(src)

"""Image-level rank engines (SPEC section 6).

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

import logging
import os
import threading
import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from harness.errors import RetrievalError

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
#: (query, row) pairs per block of the exact float64 measurement of ``d``.
EXACT_BLOCK = 16
#: (query, row) pairs per call when whole frames are measured exactly (bf16's undecided frames).
EXACT_PAIRS_PER_CALL = 1 << 16
#: float64 values per block when whole frames are measured (many rows per numpy call: the
#: per-call overhead, not the arithmetic, bounds small blocks).
FRAME_BLOCK_VALUES = 1 << 17
#: Queries per block when bf16's per-frame minima are decided (a (block, L) float64 temporary).
RANK_ROWS = 256
#: Unit roundoff of float32 (round to nearest).
F32_U = 2.0**-24
#: Unit roundoff of a float32 product's inputs under ``torch.set_float32_matmul_precision``:
#: "high" lets a product round its inputs to TF32 (10-bit fraction), "medium" to bfloat16.
MATMUL_INPUT_U = {"highest": 0.0, "high": 2.0**-11, "medium": 2.0**-8}
#: Unit roundoff of bfloat16 (8 significant bits, round to nearest).
BF16_U = 2.0**-8
#: The candidate product's arithmetic: float32 (ranks from its minima), or bfloat16 (the frames
#: its error bound cannot decide measured exactly: :func:`_exact_ranks`).
RANK_PRECISIONS = ("fp32", "bf16")


@dataclass(frozen=True)
class Ranks:
    """Per query subimage: rank of its ground-truth place, list length, distance, place size."""

    rank: np.ndarray  # (n,) int64
    L: np.ndarray  # (n,) int64: 1 + frames outside the ground-truth place
    dist: np.ndarray  # (n,) float64
    exact: np.ndarray  # (n,) bool: False where an approximate engine could only bound the rank
    place_size: np.ndarray  # (n,) int64: frames of the place that are in the database


def place_columns(
    frame_ids: np.ndarray, gt_frame: np.ndarray, place: Sequence[np.ndarray] | None
) -> list[np.ndarray]:
    """Per query, the database columns (sorted frame ids) of its ground-truth place.

    G must be present.
    """
    L = len(frame_ids)
    col = np.searchsorted(frame_ids, gt_frame)
    if L == 0 or np.any(col >= L) or np.any(frame_ids[np.minimum(col, L - 1)] != gt_frame):
        raise RetrievalError("a ground-truth frame has no subimage in the database")
    if place is None:
        return [np.array([c]) for c in col]
    if len(place) != len(gt_frame):
        raise RetrievalError(
            f"place must hold one entry per query ({len(gt_frame)}), got {len(place)}"
        )
    out = []
    for c, p in zip(col, place, strict=True):
        p = np.asarray(p)
        pc = np.searchsorted(frame_ids, p)
        ok = (pc < L) & (frame_ids[np.minimum(pc, L - 1)] == p)
        out.append(
            np.union1d(pc[ok], [c])
        )  # frames of the place without subimages are not in the list
    return out


def frame_layout(db_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order of database rows grouped by frame, the frame ids in that order, and group starts."""
    order = np.argsort(db_frame, kind="stable")
    f = db_frame[order]
    starts = (
        np.concatenate([[0], np.nonzero(f[1:] != f[:-1])[0] + 1])
        if len(f)
        else np.zeros(0, np.int64)
    )
    return order, f[starts], starts


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


_local = threading.local()


def workspace(name: str, numel: int, device: torch.device) -> torch.Tensor:
    """A flat float32 buffer of at least ``numel`` elements, kept for the calling thread.

    A fresh buffer of tens of megabytes pays a page fault per 4 KiB on first touch, which
    costs a small ranking call as much as a tenth of its matrix products; reused, it costs
    nothing. The buffer grows to the largest size asked and lives as long as the thread. Device
    memory is not kept: a CUDA buffer is allocated per call.
    """
    if device.type != "cpu":
        return torch.empty(max(numel, 1), dtype=torch.float32, device=device)[:numel]
    bufs: dict[tuple[str, str], torch.Tensor] = _local.__dict__.setdefault("bufs", {})
    key = (name, str(device))
    buf = bufs.get(key)
    if buf is None or buf.numel() < numel:
        buf = bufs[key] = torch.empty(max(numel, 1), dtype=torch.float32, device=device)
    return buf[:numel]


def scratch(name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """:func:`workspace` for numpy: an uninitialised array of ``shape``, kept for the thread."""
    bufs: dict[str, np.ndarray] = _local.__dict__.setdefault("arrays", {})
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buf = bufs.get(name)
    if buf is None or buf.nbytes < nbytes:
        buf = bufs[name] = np.empty(max(nbytes, 1), np.uint8)
    out: np.ndarray = buf[:nbytes].view(dtype).reshape(shape)
    return out


def expansion_error_factor(dim: int) -> float:
    """``c`` with ``|v - |q - b|^2| <= c (|q| + |b|)^2`` for the fast value ``v`` of any pair.

    ``v = fl(fl(qn + bn) - 2 fl(q.b))`` (clamped at 0), where ``qn``, ``bn`` are the float32
    squared norms. A float32 dot product of ``dim`` terms, summed in any order, is off by at most
    ``g_dim sum |q_i b_i| <= g_dim |q||b|`` (``g_n = n u / (1 - n u)``, Higham, Accuracy and
    Stability of Numerical Algorithms, 3.1); each norm by ``g_(dim+3) |.|^2`` (sum, square root,
    square), and the two additions add ``u`` of their operands each. All of it is below
    ``g_(dim+8) (|q| + |b|)^2``, with ``|q|`` taken from its float32 value (a relative ``g``
    larger at most: the divisor ``1 - 2g`` covers it). A product whose inputs may be rounded
    (TF32, bfloat16: :data:`MATMUL_INPUT_U`) adds ``2 u_in |q||b|``. ``inf`` where ``dim`` is so
    large that the bound says nothing (every row of the place is then measured).
    """
    nu = (dim + 8) * F32_U
    if nu >= 0.25:
        return float("inf")
    g = nu / (1 - nu)
    u_in = MATMUL_INPUT_U.get(torch.get_float32_matmul_precision(), 2.0**-8)
    return (g + 2 * u_in) / (1 - 2 * g) * (1 + 1e-6)


def bf16_error_factor(dim: int) -> float:
    """:func:`expansion_error_factor`'s ``c`` for a bfloat16 product of float32 vectors.

    The product rounds each input to bfloat16 (``|q~ . b~ - q . b| <= (2u + u^2) |q||b|``,
    ``u`` = :data:`BF16_U`), accumulates in float32 (``g_dim`` of the rounded inputs, at most
    ``(1 + u)^2`` larger) and, on CPU, rounds the dot product to bfloat16 (``u`` of it). Twice
    that error (the expansion's ``-2 q.b``), with ``|q||b| <= (|q| + |b|)^2 / 4``, is added to the
    float32 expansion's own ``c`` (norms and additions in float32). The vectors are first
    centred (``q - m``, ``b - m`` in float32, norms taken of the centred ones): each centred vector
    is within ``u32 |.|`` of its exact value, which moves the squared distance by at most
    ``3 u32 (|q| + |b|)^2``, also added. ``inf`` where ``dim`` is so large that the bound says
    nothing.
    """
    nu = (dim + 8) * F32_U
    if nu >= 0.25:
        return float("inf")
    g, u = nu / (1 - nu), BF16_U
    dot = (2 * u + u * u) + g * (1 + u) ** 2 + u * (1 + u) ** 2 * (1 + g)
    return (g / (1 - 2 * g) + 2 * dot / 4 + 3 * F32_U) * (1 + 1e-6)


def _sqdist_into(
    query: torch.Tensor, qn: torch.Tensor, block: torch.Tensor, bn: torch.Tensor, out: torch.Tensor
) -> torch.Tensor:
    """Squared L2 distances by the expansion, written into ``out`` (no allocation), clamped at 0."""
    torch.add(qn, bn[None, :], out=out)
    return out.addmm_(query, block.T, alpha=-2.0).clamp_min_(0)


def _sqdist_bf16_into(
    query: torch.Tensor, qn: torch.Tensor, block: torch.Tensor, bn: torch.Tensor, out: torch.Tensor
) -> torch.Tensor:
    """:func:`_sqdist_into` with the product in bfloat16 (``query`` and ``block`` bfloat16).

    The norms stay float32; the product accumulates in float32 (CUDA's reduced-precision
    reduction is turned off for the call) and its bfloat16 result is widened into ``out``.
    """
    torch.add(qn, bn[None, :], out=out)
    if query.device.type == "cuda":
        flag = torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction
        torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction = False
        try:
            dot = query @ block.T
        finally:
            torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction = flag
    else:
        dot = query @ block.T
    return out.add_(dot, alpha=-2.0).clamp_min_(0)


def _frame_min(d2: torch.Tensor, lens: np.ndarray, idx: torch.Tensor | None) -> torch.Tensor:
    """(n, k) minimum of ``d2``'s columns over each of k frames of ``lens`` rows (in order).

    ``idx``: None where every frame has the same length; otherwise :func:`_pad_index`'s columns.
    """
    n, k = d2.shape[0], len(lens)
    if k == 0:
        return torch.full((n, 0), float("inf"), dtype=torch.float32, device=d2.device)
    width = int(lens.max())
    if idx is None:
        return d2.view(n, k, width).amin(2)
    return torch.index_select(d2, 1, idx).view(n, k, width).amin(2)


def _pad_index(lens: np.ndarray, device: torch.device) -> torch.Tensor | None:
    """Columns padding each frame's rows to the longest with repeats of its last row.

    A repeat leaves the minimum as it is. None where the frames are of one length (a reshape does).
    """
    if len(lens) == 0 or int(lens.min()) == int(lens.max()):
        return None
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    offs = np.minimum(np.arange(int(lens.max()))[None, :], lens[:, None] - 1)
    return torch.from_numpy((starts[:, None] + offs).ravel()).to(device)


def frame_min_sqdist_chunk(
    query: torch.Tensor, qn: torch.Tensor, block: torch.Tensor, lengths: torch.Tensor
) -> torch.Tensor:
    """(n, k) smallest squared L2 distance from each query to each of k frames in ``block``.

    ``block`` holds the frames' rows one frame after another (``lengths`` rows each). The minimum
    over a frame's rows is a reshape and ``amin``: frames of equal length need no copy; otherwise
    each frame's rows are padded to the longest with repeats of its last row, one
    ``index_select`` of the product. Exact: the same minima as any other order of the same values.
    """
    bn = torch.linalg.vector_norm(block, dim=1).square_()  # fused: no (rows x D) temporary
    out = torch.empty((query.shape[0], block.shape[0]), dtype=torch.float32, device=query.device)
    lens = lengths.cpu().numpy().astype(np.int64)
    d2 = _sqdist_into(query, qn, block, bn, out)
    return _frame_min(d2, lens, _pad_index(lens, query.device))


def image_ranks(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    gt_frame: np.ndarray,
    place: Sequence[np.ndarray] | None = None,
    *,
    chunk_rows: int = 8192,
    query_batch: int = 1024,
    device: str | torch.device = "cpu",
    memory_mb: float = 1024.0,
    precision: str = "fp32",
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
    error bound and is measured exactly where the bound cannot decide (:func:`_exact_ranks`):
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
        chunk_rows: Database rows per streamed chunk.
        query_batch: Queries per matrix product.
        device: ``"cpu"`` or ``"cuda"`` (float32 products; float16 rows converted on the device).
        memory_mb: Budget (MiB) of the per-group (queries x frames) matrices, :data:`CELL_BYTES` per
            cell.
        precision: The candidate product: ``fp32``, or ``bf16`` (centred vectors, a bfloat16
            product: its bound, :func:`bf16_error_factor`, leaves frames to measure exactly).
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
    _check_inputs(query_desc, db_desc, db_frame, gt_frame, precision)
    order, frame_ids, starts = frame_layout(db_frame)
    L = len(frame_ids)
    pcols = place_columns(frame_ids, gt_frame, place)
    n = len(query_desc)
    group = max(1, int(memory_mb * 2**20 // (CELL_BYTES * max(L, 1))))
    chunk_rows = _chunk_rows(chunk_rows, torch.device(device), db_desc.shape[1])
    rank, Lq, dist = (np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.float64))
    for g0 in range(0, n, group):
        g = slice(g0, min(n, g0 + group))
        rank[g], Lq[g], dist[g] = _rank_group(
            query_desc[g],
            db_desc,
            order,
            starts,
            pcols[g],
            chunk_rows,
            query_batch,
            torch.device(device),
            precision == "bf16",
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

    ``qi``, ``pc``: the (query, place frame) pairs. Frames of the place never count.
    """
    n, L = fm.shape
    dev = fm.device
    in_place = torch.zeros((n, L), dtype=torch.bool, device=dev)
    in_place[torch.from_numpy(qi).to(dev), torch.from_numpy(pc).to(dev)] = True
    dg = fm.masked_fill(~in_place, float("inf")).amin(1, keepdim=True)
    rank = (((fm < dg) & ~in_place).sum(1) + 1).cpu().numpy().astype(np.int64)
    Lq = (L - in_place.sum(1) + 1).cpu().numpy().astype(np.int64)
    return rank, Lq


def _rank_group(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    order: np.ndarray,
    starts: np.ndarray,
    pcols: list[np.ndarray],
    chunk_rows: int,
    query_batch: int,
    dev: torch.device,
    bf16: bool,
    stats: dict[str, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`image_ranks` for one group of queries: one pass over the database.

    The pass writes into buffers allocated once (a chunk's float32 rows, one batch's distances):
    a fresh multi-megabyte tensor per chunk costs its page faults, as much as the float16
    conversion itself. While a chunk's rows and distances are at hand, the rows of each query's
    place that may hold its exact ``d`` are measured (:class:`_ExactPlace`): no second pass.
    ``bf16``: the products in bfloat16 of vectors centred on the group's mean query (smaller
    norms, a tighter bound), each frame's largest centred row norm kept for the bound.
    """
    L, n = len(starts), len(query_desc)
    contiguous = bool(np.all(order == np.arange(len(order))))
    bounds = np.concatenate([starts, [len(order)]])
    lhs, qnorms, center = _query_batches(query_desc, query_batch, dev, bf16)
    sqdist = _sqdist_bf16_into if bf16 else _sqdist_into
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
    exact = _ExactPlace(
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
        idx = _pad_index(lens, dev)
        cqr, crow = _place_rows(pair_q, pair_c, bounds, f0, f1)
        vals = np.empty(len(cqr), np.float32)  # fast values of those rows, batch by batch
        for bi, (q, qn) in enumerate(zip(lhs, qnorms, strict=True)):
            q0 = bi * query_batch
            d2 = sqdist(q, qn, rhs, bn, d2_buf[: len(q) * (r1 - r0)].view(len(q), -1))
            fm[q0 : q0 + len(q), f0:f1] = _frame_min(d2, lens, idx)
            mine = np.nonzero((cqr >= q0) & (cqr < q0 + len(q)))[0]
            if len(mine):
                sel = (
                    torch.from_numpy(cqr[mine] - q0).to(dev),
                    torch.from_numpy(crow[mine]).to(dev),
                )
                vals[mine] = d2[sel].cpu().numpy()
        # Once per chunk, not per batch: the exact step's threads run while torch's OpenMP threads
        # spin after their last product (measured: a few milliseconds each time).
        if dev.type == "cpu":  # the chunk's rows, in memory and float32 already
            exact.add(cqr, vals, bn_host[crow], query_desc, block.numpy(), crow)
        else:  # the device's copy is not read back: the rows are read from the database
            exact.add(cqr, vals, bn_host[crow], query_desc, db_desc, order[r0 + crow])
    if not bf16:  # fp32: the fast minima compared with each other (see :func:`image_ranks`)
        rank, Lq = _place_ranks(fm, qi, pc)
    else:
        measure = _FrameMeasure(query_desc, db_desc, order, bounds)
        rank, Lq = _exact_ranks(fm, qi, pc, exact, fmax, measure, stats)
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


@dataclass(frozen=True)
class _FrameMeasure:
    """What measuring a query's distance to a whole frame exactly needs: the rows and the frames."""

    query_desc: np.ndarray
    db_desc: np.ndarray
    order: np.ndarray
    bounds: np.ndarray

    def frame_min(self, qq: np.ndarray, ff: np.ndarray) -> np.ndarray:
        """Exact (float64) smallest squared distance from query ``qq[k]`` to frame ``ff[k]``."""
        out = np.empty(len(qq), np.float64)
        lens = self.bounds[ff + 1] - self.bounds[ff]
        per = max(1, EXACT_PAIRS_PER_CALL // max(int(lens.max(initial=1)), 1))
        for s in range(0, len(qq), per):
            q, f, n = qq[s : s + per], ff[s : s + per], lens[s : s + per]
            rep = np.repeat(np.arange(len(q)), n)
            first = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64)
            rows = self.order[self.bounds[f][rep] + np.arange(len(rep)) - first[rep]]
            block = max(EXACT_BLOCK, FRAME_BLOCK_VALUES // self.db_desc.shape[1])
            d2 = _exact_pairs(self.query_desc, q[rep], self.db_desc, rows, block)
            out[s : s + per] = np.minimum.reduceat(d2, first)
        return out


def _exact_ranks(
    fm: torch.Tensor,
    qi: np.ndarray,
    pc: np.ndarray,
    exact: _ExactPlace,
    fmax: np.ndarray,
    measure: _FrameMeasure,
    stats: dict[str, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Rank and L from the product's per-frame minima ``fm``, decided against the exact ``d``.

    A frame F outside the place is within ``E = c (|q| + max |b in F|)^2`` of its true minimum
    (``c``: :func:`expansion_error_factor` or :func:`bf16_error_factor`): it counts when
    ``fm + E < d^2``, not when ``fm - E > d^2``, and is measured exactly (:class:`_FrameMeasure`)
    in between, where it counts when strictly closer than ``d`` (ties in the query's favour).
    """
    fmn = fm.cpu().numpy()
    n, L = fmn.shape
    by_q = np.zeros(n + 1, np.int64)
    np.add.at(by_q, qi + 1, 1)
    by_q = np.cumsum(by_q)  # qi is sorted by query: query i's place columns are pc[by_q[i]:..]
    rank = np.ones(n, np.int64)
    todo_q, todo_f = [], []
    for s in range(0, n, RANK_ROWS):
        e = min(n, s + RANK_ROWS)
        v = fmn[s:e].astype(np.float64)
        err = exact.factor * (exact.qnorm[s:e, None] + fmax[None, :]) ** 2
        d2 = exact.best[s:e, None]
        outside = np.ones((e - s, L), bool)
        outside[qi[by_q[s] : by_q[e]] - s, pc[by_q[s] : by_q[e]]] = False
        sure = (v + err < d2) & outside
        maybe = (v - err <= d2) & ~sure & outside
        rank[s:e] += sure.sum(1)
        q, f = np.nonzero(maybe)
        todo_q.append(q + s)
        todo_f.append(f)
    qq = np.concatenate(todo_q) if todo_q else np.zeros(0, np.int64)
    ff = np.concatenate(todo_f) if todo_f else np.zeros(0, np.int64)
    if len(qq):
        closer = measure.frame_min(qq, ff) < exact.best[qq]
        rank += np.bincount(qq[closer], minlength=n)
    Lq = L - np.diff(by_q) + 1
    stats["compared"] = stats.get("compared", 0) + int((Lq - 1).sum())
    stats["measured_exactly"] = stats.get("measured_exactly", 0) + len(qq)
    return rank, Lq.astype(np.int64)


class _ExactPlace:
    """``d`` = the exact smallest L2 distance from each query to the rows of its place.

    Fed, chunk by chunk, with (query, row, fast value) of every row of every query's place.
    The fast value ``v`` of a pair is within ``E = c (|q| + |b|)^2`` of its true squared distance
    (:func:`expansion_error_factor`), so a row can hold the minimum only if ``v - E`` is at most
    the smallest upper bound known for the query: ``upper``, the least exact value measured so
    far (or ``v + E`` of a row not measured). Per chunk, each query's row of least ``v`` is
    measured first, which usually leaves none of the others under the bound. Rows measured by
    differences in float64 (:func:`_exact_pairs`), the value each pair gets on its own; the
    minimum is taken over them. The rows never measured cannot hold it, so ``d`` is the same as
    measuring every row of the place.
    """

    def __init__(self, qn: np.ndarray, factor: float) -> None:
        self.qnorm = np.sqrt(qn)
        self.factor = factor  # the product's error bound (:func:`expansion_error_factor`)
        self.best = np.full(len(qn), np.inf)  # least exact squared distance measured
        self.upper = np.full(len(qn), np.inf)  # least known upper bound on it
        self.measured = 0  # (query, row) pairs measured, for the tests and the bench

    def _select(self, ii: np.ndarray, v: np.ndarray, bn: np.ndarray) -> tuple[np.ndarray, ...]:
        """Indices of the pairs to measure now: each query's least ``v``, then the rest."""
        vv = v.astype(np.float64)
        err = self.factor * (self.qnorm[ii] + np.sqrt(bn)) ** 2
        by = np.lexsort((vv, ii))  # by query, then fast value
        iis = ii[by]
        first = np.flatnonzero(np.concatenate([[True], iis[1:] != iis[:-1]]))
        own = iis[first]  # each query once
        self.upper[own] = np.minimum(self.upper[own], np.minimum.reduceat((vv + err)[by], first))
        return by[first], vv - err

    def _after_lead(self, ii: np.ndarray, lo: np.ndarray, lead: np.ndarray) -> np.ndarray:
        """The pairs other than the lead ones whose lower bound reaches the query's upper bound."""
        slack = self.upper[ii] * (1 + 1e-9)  # float64 rounding of the measured values
        rest = lo <= slack
        rest[lead] = False
        return np.nonzero(rest)[0]

    def _measure(
        self, ii: np.ndarray, query_desc: np.ndarray, dsrc: np.ndarray, di: np.ndarray
    ) -> None:
        """Measure the pairs (query ``ii``, row ``di`` of ``dsrc``) and keep each query's least."""
        if len(ii):
            np.minimum.at(self.best, ii, _exact_pairs(query_desc, ii, dsrc, di))
            self.upper[ii] = np.minimum(self.best[ii], self.upper[ii])
            self.measured += len(ii)

    def add(
        self,
        ii: np.ndarray,
        v: np.ndarray,
        bn: np.ndarray,
        query_desc: np.ndarray,
        dsrc: np.ndarray,
        di: np.ndarray,
    ) -> None:
        """Pairs of query ``ii`` and row ``di`` of ``dsrc`` (a chunk's rows or the database).

        ``v``: their fast values; ``bn``: the rows' fast squared norms.
        """
        if not len(ii):
            return
        lead, lo = self._select(ii, v, bn)
        self._measure(ii[lead], query_desc, dsrc, di[lead])
        rest = self._after_lead(ii, lo, lead)  # bounded by the lead rows' exact values
        self._measure(ii[rest], query_desc, dsrc, di[rest])


def _exact_pairs(
    qsrc: np.ndarray, qi: np.ndarray, dsrc: np.ndarray, di: np.ndarray, block: int = EXACT_BLOCK
) -> np.ndarray:
    """Squared L2 distance of each pair (``qsrc[qi[k]]``, ``dsrc[di[k]]``).

    By differences in float64 (float16 and float32 rows widen exactly), squared, then numpy's
    pairwise sum of each row: the same bits as ``((b.astype(np.float64) - q) ** 2).sum()`` for
    the pair alone. The pairs are split between :func:`_exact_pool`'s threads (numpy releases
    the GIL), each working in blocks of :data:`EXACT_BLOCK` pairs in buffers of its own kept
    between calls (:func:`scratch`). Own buffers matter: when one thread writes the squares and
    another sums them, every block's cache lines cross between cores, which measured up to three
    times slower on this project's machines. ``block``: pairs per block (the same bits whatever
    it is: each row is summed alone).
    """
    n_pairs = len(qi)
    out = np.empty(n_pairs, np.float64)
    if n_pairs == 0:
        return out
    pool, workers = _exact_pool()
    per = -(-n_pairs // max(1, min(workers, n_pairs // block)))
    parts = [(s, min(n_pairs, s + per)) for s in range(0, n_pairs, per)]

    def work(part: tuple[int, int]) -> None:
        acc = scratch("exact_acc", (block, dsrc.shape[1]), np.float64)
        for s in range(part[0], part[1], block):
            k = min(part[1], s + block) - s
            a = acc[:k]
            a[...] = dsrc[di[s : s + k]]  # gathered, widened
            np.subtract(a, qsrc[qi[s : s + k]], out=a)
            np.square(a, out=a)
            out[s : s + k] = a.sum(1)

    if len(parts) == 1:
        work(parts[0])
    else:
        list(pool.map(work, parts))
    return out


_POOL: list[tuple[ThreadPoolExecutor, int]] = []


def _exact_pool() -> tuple[ThreadPoolExecutor, int]:
    """The exact step's threads: as many as torch's (at most 8), started once per process."""
    workers = max(1, min(8, torch.get_num_threads()))
    if not _POOL or _POOL[0][1] != workers:
        if _POOL:
            _POOL.pop()[0].shutdown(wait=False)
        _POOL.append((ThreadPoolExecutor(workers, thread_name_prefix="dbl-exact"), workers))
    return _POOL[0]


os.register_at_fork(after_in_child=_POOL.clear)  # a forked child has no threads of its parent


def image_ranks_faiss(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    gt_frame: np.ndarray,
    place: Sequence[np.ndarray] | None = None,
    *,
    k: int = 256,
    nlist: int = 0,
    nprobe: int = 8,
    seed: int = 0,
) -> Ranks:
    """Approximate ranks from a faiss top-k subimage search.

    ``d`` is computed exactly from the place's own rows. Frames outside the place among the top k
    with a smaller distance are counted; when the k-th distance is still below ``d`` frames
    beyond the top k may be better too, so the rank is a lower bound and ``exact`` is False.
    ``place`` as in :func:`image_ranks`.
    """
    try:
        import faiss
    except ImportError as err:  # pragma: no cover - faiss is in the dev extra
        raise RetrievalError(
            "the faiss engine needs faiss: pip install 'dbl-harness[faiss]'"
        ) from err
    q = np.ascontiguousarray(query_desc, dtype=np.float32)
    db = np.ascontiguousarray(db_desc, dtype=np.float32)
    d = db.shape[1]
    if nlist > 0:
        index: Any
        quant = faiss.IndexFlatL2(d)
        index = faiss.IndexIVFFlat(quant, d, nlist)
        rs = np.random.default_rng(seed)
        index.train(db[rs.choice(len(db), size=min(len(db), max(nlist * 39, 1000)), replace=False)])
        index.nprobe = nprobe
    else:
        index = faiss.IndexFlatL2(d)
    index.add(db)
    kk = min(k, len(db))
    D, idx = index.search(q, kk)
    order, frame_ids, starts = frame_layout(np.asarray(db_frame))
    L = len(frame_ids)
    pcols = place_columns(frame_ids, np.asarray(gt_frame), place)
    rank = np.empty(len(q), np.int64)
    dist = np.empty(len(q), np.float64)
    exact = np.empty(len(q), bool)
    bounds = np.concatenate([starts, [len(order)]])
    for i in range(len(q)):
        rows = np.concatenate([order[bounds[c] : bounds[c + 1]] for c in pcols[i]])
        dg2 = float(((db[rows].astype(np.float64) - q[i]) ** 2).sum(1).min())
        found = idx[i] >= 0
        fr = np.asarray(db_frame)[idx[i][found]]
        dd = D[i][found]
        members = set(frame_ids[pcols[i]].tolist())
        better = {f for f, v in zip(fr.tolist(), dd, strict=True) if v < dg2 and f not in members}
        rank[i] = 1 + len(better)
        dist[i] = np.sqrt(dg2)
        exact[i] = bool(len(dd) == len(db) or (len(dd) and dd[-1] >= dg2))
    sizes = np.array([len(c) for c in pcols], np.int64)
    return Ranks(rank, L - sizes + 1, dist, exact, sizes)

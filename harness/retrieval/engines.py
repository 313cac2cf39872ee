"""Image-level rank engines (SPEC section 6).

For a query subimage q whose ground-truth reference frame is G, with the ground-truth *place*
P(G) (the reference frames near G; P(G) = {G} when no place is given):
``dist(q, F)`` is the smallest L2 distance from q to any subimage of frame F;
``d(q) = min over F in P(G) of dist(q, F)``, computed exactly (differences, not the expansion);
``rank(q) = 1 + #{F outside P(G) : dist(q, F) < d(q)}`` (ties counted in q's favour);
``L = 1 + #frames outside P(G)``; ``r = rank / L``; ``r' = (L + 1 - rank) / L``.

The exact engine computes the per-frame minimum with batched matrix products over chunks of the
database, so memory is bounded by ``query_batch x (chunk_rows + L)`` whatever the database size.
An optional faiss engine returns the same quantities from a top-k search (exact for every query
whose ground-truth frame is found among the top k; otherwise a lower bound, flagged).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..errors import RetrievalError

log = logging.getLogger(__name__)

#: Bytes per (query, frame) cell a group holds at its peak: the float32 minima, the place mask, the
#: masked copy and the comparison's boolean temporaries.
CELL_BYTES = 16
# : Database rows per chunk on a CUDA device (at least): larger than on CPU, where a chunk should
# stay in cache.
CUDA_CHUNK_ROWS = 65536


@dataclass(frozen=True)
class Ranks:
    """Per query subimage: rank of its ground-truth place, list length, distance, place size."""

    rank: np.ndarray  # (n,) int64
    L: np.ndarray  # (n,) int64: 1 + frames outside the ground-truth place
    dist: np.ndarray  # (n,) float64
    exact: np.ndarray  # (n,) bool: False where an approximate engine could only bound the rank
    place_size: np.ndarray  # (n,) int64: frames of the place that are in the database


def _place_columns(
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


def _frame_layout(db_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def frame_min_sqdist_chunk(
    query: torch.Tensor, qn: torch.Tensor, block: torch.Tensor, lengths: torch.Tensor
) -> torch.Tensor:
    """(n, k) smallest squared L2 distance from each query to each of k frames in ``block``.

    ``block`` holds the frames' rows one frame after another (``lengths`` rows each). The minimum
    over a frame's rows is a reshape and ``amin``: frames of equal length need no copy; otherwise
    each frame's rows are padded to the longest with repeats of its last row (a repeat leaves
    the minimum as it is), one ``index_select`` of the product. Exact: the same minima as any
    other order of the same values.
    """
    bn = torch.linalg.vector_norm(block, dim=1).square_()  # fused: no (rows x D) temporary
    d2 = torch.addmm(qn + bn[None, :], query, block.T, alpha=-2.0).clamp_min_(0)
    n, k = query.shape[0], len(lengths)
    if k == 0:
        return torch.full((n, 0), float("inf"), dtype=torch.float32, device=query.device)
    lens = lengths.cpu().numpy().astype(np.int64)
    width = int(lens.max())
    if int(lens.min()) == width:
        return d2.view(n, k, width).amin(2)
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    offs = np.minimum(np.arange(width)[None, :], lens[:, None] - 1)  # repeat each frame's last
    idx = torch.from_numpy((starts[:, None] + offs).ravel()).to(query.device)
    return torch.index_select(d2, 1, idx).view(n, k, width).amin(2)


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
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact image-level ranks of the ground-truth places.

    The database is streamed in chunks of about ``chunk_rows`` rows (cut at frame boundaries), each
    read once and converted to float32 on the fly, so ``db_desc`` may be a float16 memmap of any
    size. Memory is bounded by ``memory_mb``, not by the data: queries are ranked in groups
    whose (group, frames) per-frame minimum and place mask fit in it (each group streams the
    database once), plus one chunk of ``chunk_rows`` rows and its (query_batch x chunk_rows)
    distances. Ranks compare the per-frame minima of the fast matrix-product path with each
    other; ``d`` is then recomputed exactly from the place's own rows (differences, float64), so
    a query equal to a database row gets ``d = 0``.

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

    Returns:
        ``rank`` (n,) int64, ``L`` (n,) int64 (1 + frames outside the place), ``dist`` (n,)
        float64 exact L2 distance ``d`` to the place.

    Raises:
        RetrievalError: shapes disagree or a ground-truth frame has no database row.
    """
    db_frame = np.asarray(db_frame)
    gt_frame = np.asarray(gt_frame)
    if query_desc.ndim != 2 or db_desc.ndim != 2 or query_desc.shape[1] != db_desc.shape[1]:
        raise RetrievalError(
            f"descriptor shapes disagree: query {query_desc.shape}, database {db_desc.shape}"
        )
    if len(db_frame) != len(db_desc) or len(gt_frame) != len(query_desc):
        raise RetrievalError("db_frame must align with db_desc and gt_frame with query_desc")
    order, frame_ids, starts = _frame_layout(db_frame)
    L = len(frame_ids)
    pcols = _place_columns(frame_ids, gt_frame, place)
    n = len(query_desc)
    group = max(1, int(memory_mb * 2**20 // (CELL_BYTES * max(L, 1))))
    if (
        torch.device(device).type == "cuda"
    ):  # device memory is large and the copy costs more than the product
        chunk_rows = max(chunk_rows, CUDA_CHUNK_ROWS)
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
        )
    return rank, Lq, dist


def _rank_group(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    order: np.ndarray,
    starts: np.ndarray,
    pcols: list[np.ndarray],
    chunk_rows: int,
    query_batch: int,
    dev: torch.device,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`image_ranks` for one group of queries: one pass over the database."""
    L, n = len(starts), len(query_desc)
    contiguous = bool(np.all(order == np.arange(len(order))))
    bounds = np.concatenate([starts, [len(order)]])
    queries = [
        torch.from_numpy(
            np.ascontiguousarray(query_desc[s : s + query_batch], dtype=np.float32)
        ).to(dev)
        for s in range(0, n, query_batch)
    ]
    qnorms = [torch.linalg.vector_norm(q, dim=1, keepdim=True).square_() for q in queries]
    fm = torch.empty((n, L), dtype=torch.float32, device=dev)
    for f0, f1 in _chunks(starts, len(order), chunk_rows):
        r0, r1 = int(bounds[f0]), int(bounds[f1])
        rows = np.ascontiguousarray(db_desc[r0:r1] if contiguous else db_desc[order[r0:r1]])
        with warnings.catch_warnings():  # a read-only memmap view; the tensor is only read
            warnings.simplefilter("ignore", UserWarning)
            block = (
                torch.from_numpy(rows).to(dev).float()
            )  # float16 -> float32 in torch (multi-threaded)
        lengths = torch.from_numpy(np.diff(bounds[f0 : f1 + 1])).to(dev)
        for b, (q, qn) in enumerate(zip(queries, qnorms, strict=True)):
            fm[b * query_batch : b * query_batch + len(q), f0:f1] = frame_min_sqdist_chunk(
                q, qn, block, lengths
            )
    qi = np.repeat(np.arange(n), [len(c) for c in pcols])
    pc = np.concatenate(pcols) if n else np.zeros(0, np.int64)
    in_place = torch.zeros((n, L), dtype=torch.bool, device=dev)
    in_place[torch.from_numpy(qi).to(dev), torch.from_numpy(pc).to(dev)] = True
    dg = fm.masked_fill(~in_place, float("inf")).amin(1, keepdim=True)
    rank = (
        (((fm < dg) & ~in_place).sum(1) + 1).cpu().numpy().astype(np.int64)
    )  # place frames never count
    Lq = (L - in_place.sum(1) + 1).cpu().numpy().astype(np.int64)
    fm_np = fm.cpu().numpy()
    del fm, in_place
    dist = _exact_place_dist(
        query_desc, db_desc, order, bounds, pcols, fm_np, dg[:, 0].cpu().numpy()
    )
    return rank, Lq, dist


def _exact_place_dist(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    order: np.ndarray,
    bounds: np.ndarray,
    pcols: list[np.ndarray],
    fm: np.ndarray,
    dg: np.ndarray,
) -> np.ndarray:
    """``d`` = the exact smallest L2 distance from each query to the rows of its place.

    Only the place's frames whose fast-path minimum lies within the expansion's error of the
    best are recomputed (usually one frame), and within such a frame only the rows whose float32
    expansion lies within that error of the frame's best (usually one row): by differences in
    float64, the value every such row would get on its own, so the minimum is the same as over
    every row. The work is done frame by frame: a frame's rows are converted once and stay in
    cache while every query that needs them is measured.
    """
    n = len(pcols)
    qi: list[np.ndarray] = []
    ci: list[np.ndarray] = []
    for i, cols in enumerate(pcols):
        near = cols[fm[i, cols] <= dg[i] + 1e-2 + 1e-3 * abs(dg[i])] if len(cols) > 1 else cols
        qi.append(np.full(len(near), i, np.int64))
        ci.append(np.asarray(near, np.int64))
    q_of = np.concatenate(qi) if qi else np.zeros(0, np.int64)
    c_of = np.concatenate(ci) if ci else np.zeros(0, np.int64)
    by_frame = np.argsort(c_of, kind="stable")
    q_of, c_of = q_of[by_frame], c_of[by_frame]
    best = np.full(n, np.inf)
    cuts = np.flatnonzero(np.diff(c_of)) + 1
    for part in np.split(np.arange(len(c_of)), cuts) if len(c_of) else []:
        c = int(c_of[part[0]])
        rows32 = np.asarray(db_desc[np.sort(order[bounds[c] : bounds[c + 1]])], np.float32)
        qs = q_of[part]
        q32 = np.asarray(query_desc[qs], np.float32)
        fast = (
            (q32 * q32).sum(1)[:, None] + (rows32 * rows32).sum(1)[None, :] - 2.0 * q32 @ rows32.T
        )
        lim = fast.min(1, keepdims=True)
        near_rows = fast <= lim + 1e-2 + 1e-3 * np.abs(lim)
        for j, i in enumerate(qs):
            q = np.asarray(query_desc[i], np.float64)
            sel = rows32[near_rows[j]].astype(np.float64)
            best[i] = min(best[i], float(((sel - q) ** 2).sum(1).min()))
    out: np.ndarray = np.sqrt(best)
    return out


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
    order, frame_ids, starts = _frame_layout(np.asarray(db_frame))
    L = len(frame_ids)
    pcols = _place_columns(frame_ids, np.asarray(gt_frame), place)
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

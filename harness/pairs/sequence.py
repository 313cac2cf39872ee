"""Pairs by sequence (method §13.2): one order-keeping alignment of the query run to the map run.

Two runs of one route keep their order. The query run is aligned to the map run as a whole, by
dynamic programming over the frames' distance matrix (a Viterbi path): each query frame takes one
map frame, the next query frame a map frame at most ``max_step`` further on (0: the query stood
still or ran slower; more than 1: the map did), every step other than one frame costing
``step_cost``. So a stretch whose own evidence is weak (fog, a dim platform) takes its place from
the path through it, and can never be pulled onto a few map frames ahead of it or behind it (a
hub): the order of the ride forbids it.

- **The cost of a cell** is the frame distance over the geometric mean of its row's and its
  column's medians (SeqSLAM's contrast enhancement in both directions: a map frame that is near
  everything, as a foggy or dim one is, gains nothing by it), capped at ``cap``: a cell worse
  than a typical distance is no evidence either way, so one bad frame costs no more than that.
- **Map frames that carry no place** (dark, blank: :mod:`harness.pairs.place`) keep their place
  in the map's order, at the cap: the path runs through them, and a query frame it places there
  is left unpaired, named (its place's map frame shows nothing).
- **Either way round, any part, loops**: the path may start and end at any map frame, the map is
  tried in both directions (the cheaper path is the alignment), and a step may run from the map's
  last frame onto its first at the cost of two frames of no evidence: a loop driven from
  another start.

Memory: the whole path takes the distances (8 bytes a cell) and its back-pointers (1 byte); a ride
over ``[retrieval] memory_mb`` is aligned inside a band around a coarse path instead
(:func:`banded_pairs`: 13 bytes a cell of the band, the distances streamed), the same path
wherever the band holds it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from harness.pairs.frame_distances import SEQUENCE_SPEEDS, sequence_scores

#: The cost of a cell that is no evidence either way (a cell's distance over its row's and
#: column's typical one), and of a map frame that carries no place.
CAP = 1.0
#: The cost of a step other than one map frame a query frame (a stop, or another speed).
STEP_COST = 0.1
#: The most map frames one query frame's step may advance (the map's run three times as fast).
MAX_STEP = 3
#: A step from the map's last frame onto its first (a route driven as a loop, the query run
#: starting elsewhere on it) costs this many caps more: two frames' worth of no evidence.
WRAP = 2.0


#: Why a query frame of a sequence is left unpaired: the path places it where the map's frames
#: carry no place (dark, blank), or it stands on one map frame with more than
#: :data:`STOP_FRAMES` others and no evidence of its own (its cost at least :data:`WEAK` of the
#: cap: a run past either end of the map's, or a stretch the map never saw).
UNPAIRED_DARK = "its place in the map's run is a frame that carries no place"
UNPAIRED_WEAK = "the path stands still there and the frame has no evidence of its own"
STOP_FRAMES, WEAK = 5, 0.9


@dataclass(frozen=True)
class Alignment:
    """A query run's path through the map run.

    ``column``: each query frame's map frame (its column, in the map's order); ``cost``: the
    path's total cost; ``reversed``: the query runs the route the other way round.
    """

    column: np.ndarray
    cost: float
    reversed: bool


def cell_costs(dist: np.ndarray, usable: np.ndarray, cap: float) -> np.ndarray:
    """The alignment's cost of each (query frame, map frame) cell (see the module's text).

    ``dist``: (n_q, n_m) frame distances; ``usable``: (n_m,) map frames that carry a place.
    """
    d = np.asarray(dist, np.float64)
    ok = np.asarray(usable, bool)
    if not ok.any():
        return np.full(d.shape, cap)
    row = np.median(d[:, ok], axis=1)
    col = np.median(d, axis=0)
    scale = np.sqrt(np.maximum(row[:, None], 1e-12) * np.maximum(col[None, :], 1e-12))
    with np.errstate(invalid="ignore"):  # a column of no place may hold no distance (inf)
        c = np.minimum(d / scale, cap)
    c[:, ~ok] = cap
    return c


def _path(
    c: np.ndarray, max_step: int, step_cost: float, wrap_cost: float
) -> tuple[np.ndarray, float]:
    """The least-cost monotone path through ``c`` (free start and end), and its cost.

    A step may run past the map's last frame onto its first (a loop) at ``wrap_cost`` more.
    """
    nq, nm = c.shape
    back = np.zeros((nq, nm), np.int8)
    acc = c[0].copy()
    pen = step_cost * np.abs(np.arange(max_step + 1) - 1.0)
    for i in range(1, nq):
        best = acc + pen[0]
        arg = np.zeros(nm, np.int8)
        for d in range(1, min(max_step, nm - 1) + 1):
            cand = np.roll(acc, d) + pen[d]
            cand[:d] += wrap_cost  # from the map's end onto its start
            better = cand < best
            best = np.where(better, cand, best)
            arg[better] = d
        back[i] = arg
        acc = best + c[i]
    j = int(np.argmin(acc))
    total = float(acc[j])
    col = np.empty(nq, np.int64)
    for i in range(nq - 1, -1, -1):
        col[i] = j
        j = (j - int(back[i, j])) % nm
    return col, total


def align(
    dist: np.ndarray,
    usable: np.ndarray,
    max_step: int = MAX_STEP,
    step_cost: float = STEP_COST,
    cap: float = CAP,
) -> Alignment:
    """The query run aligned to the map run: each query frame's map frame, keeping both orders.

    ``dist``: (n_q, n_m) frame distances, both runs in time order; ``usable``: the map frames
    that carry a place. Both directions of the map are tried (a query run that goes the other
    way round); the cheaper path wins, the forward one on a tie.
    """
    c = cell_costs(dist, usable, cap)
    if not len(c) or not c.shape[1]:
        return Alignment(np.zeros(len(c), np.int64), 0.0, False)
    fwd, cost_f = _path(c, max_step, step_cost, WRAP * cap)
    bwd, cost_b = _path(c[:, ::-1], max_step, step_cost, WRAP * cap)
    if cost_b < cost_f:
        return Alignment(c.shape[1] - 1 - bwd, cost_b, True)
    return Alignment(fwd, cost_f, False)


def path_pairs(
    dist: np.ndarray, usable: np.ndarray, window: int, exclude: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, str]]:
    """Each query frame's map frame on the path, its evidence and rival, and who stays unpaired.

    ``dist``: the (n_q, n_m) frame distances. The evidence is SeqSLAM's sequence score of
    ``window`` frames (:func:`harness.pairs.frame_distances.sequence_scores`) at the path's cell,
    along the path's direction through the map; the rival the best score more than ``exclude``
    frames from the path's map frame. Returns the path's map frames (positions), the scores there,
    the rivals, and the query frames (positions) left unpaired with why (:data:`UNPAIRED_DARK`,
    :data:`UNPAIRED_WEAK`).
    """
    path = align(dist, usable)
    col = path.column
    masked = np.where(usable[None, :], dist, np.inf)
    seq = (
        sequence_scores(masked[:, ::-1], window)[:, ::-1]
        if path.reversed
        else sequence_scores(masked, window)
    )
    rows = np.arange(len(col))
    pos = np.arange(dist.shape[1])
    rival = np.where(np.abs(pos[None, :] - col[:, None]) > exclude, seq, np.inf)
    second = rival.min(axis=1) if rival.shape[1] else np.full(len(col), np.inf)
    cost = cell_costs(dist, usable, CAP)[rows, col]
    return col, seq[rows, col], second, _unpaired(col, cost, usable)


def _row_scores(rows: np.ndarray, at: int, window: int) -> np.ndarray:
    """Row ``at`` of :func:`harness.pairs.frame_distances.sequence_scores` of ``rows``.

    ``rows``: the query frames around it (the run's end where it ends), read alone.
    """
    n, nd = rows.shape
    half = max(window, 1) // 2
    best = np.full(nd, np.inf)
    for v in SEQUENCE_SPEEDS:
        acc, cnt = np.zeros(nd), np.zeros(nd)
        for k in range(-half, half + 1):
            off = round(v * k)
            j0, j1 = max(0, -off), min(nd, nd - off)
            if 0 <= at + k < n and j0 < j1:
                acc[j0:j1] += rows[at + k, j0 + off : j1 + off]
                cnt[j0:j1] += 1
        best = np.minimum(best, np.divide(acc, cnt, out=np.full(nd, np.inf), where=cnt > 0))
    return best


@dataclass
class _Band:
    """The banded path's per-row records.

    Back-pointers, costs and sequence scores on the band, and each row's least sequence scores
    anywhere (the rival's candidates).
    """

    lo: np.ndarray
    width: int
    nm: int
    keep: int

    def __post_init__(self) -> None:
        nq = len(self.lo)
        self.back = np.zeros((nq, self.width), np.int8)
        self.cost = np.zeros((nq, self.width), np.float32)
        self.seq = np.zeros((nq, self.width), np.float64)
        self.top_v = np.full((nq, self.keep), np.inf)
        self.top_j = np.zeros((nq, self.keep), np.int64)

    def cols(self, i: int) -> np.ndarray:
        return (self.lo[i] + np.arange(self.width)) % self.nm

    def shift(self, i: int) -> int:
        """How far row ``i``'s band starts after row ``i - 1``'s (across a loop's wrap too)."""
        return int((self.lo[i] - self.lo[i - 1] + self.nm // 2) % self.nm - self.nm // 2)

    def scored(self, u: int, s: np.ndarray) -> None:
        self.seq[u] = s[self.cols(u)]
        k = min(self.keep, len(s))
        j = np.argpartition(s, k - 1)[:k]
        self.top_v[u, :k], self.top_j[u, :k] = s[j], j


def _guide(
    rows: Callable[[np.ndarray], Iterator[np.ndarray]],
    shape: tuple[int, int],
    usable: np.ndarray,
    budget_cells: int,
) -> tuple[np.ndarray, int, bool]:
    """The band of :func:`banded_pairs` and the path's direction through the map.

    Each query frame's first map frame of the band, its width, and whether the path runs through
    the map backwards (the band then counts the map reversed). The coarse path is :func:`align`
    of every ``s``-th query frame against blocks of ``s`` map frames (each block's least
    distance), ``s`` as small as ``budget_cells`` allows.
    """
    nq, nm = shape
    s = max(1, int(np.ceil(np.sqrt(nq * nm / max(budget_cells, 1)))))
    qs, ms = np.arange(0, nq, s), np.arange(0, nm, s)
    pooled = [np.minimum.reduceat(np.where(usable, b, np.inf), ms, axis=1) for b in rows(qs)]
    coarse = align(np.concatenate(pooled), np.logical_or.reduceat(usable, ms))
    flip = coarse.reversed
    guide = (len(ms) - 1 - coarse.column) * s + (nm - 1 - (len(ms) - 1) * s) if flip else (
        coarse.column * s)  # fmt: skip
    guide = np.unwrap(guide.astype(np.float64), period=nm)  # across a loop's wrap
    width = min(2 * (4 * s + 8) + 1, nm)
    lo = np.round(np.interp(np.arange(nq), qs, guide)).astype(np.int64) - width // 2
    return lo, width, flip


def banded_pairs(
    rows: Callable[[np.ndarray], Iterator[np.ndarray]],
    shape: tuple[int, int],
    usable: np.ndarray,
    window: int,
    exclude: int,
    budget_cells: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, str]]:
    """:func:`path_pairs` for a ride too long to hold its distance matrix: banded and streamed.

    ``rows(query positions)`` yields those query frames' distance rows (to every map frame), in
    order, a block at a time; ``shape``: (n_q, n_m); ``budget_cells``: the cells the coarse
    matrix may hold. A coarse path (:func:`align` of every ``s``-th frame of both runs, ``s`` as
    small as the budget allows) gives each query frame a guide and the direction; the path is
    then :func:`align`'s inside a band of ``4 s + 8`` map frames either side of the guide, the
    distances streamed. The cells' column medians are those of 64 query frames spread over the
    run (the whole run's in :func:`align`). Memory: 13 bytes a cell of the band, ``window`` rows
    of distances and the coarse matrix.
    """
    nq, nm = shape
    lo, width, flip = _guide(rows, shape, np.asarray(usable, bool), budget_cells)
    sample = np.unique(np.linspace(0, nq - 1, min(nq, 64)).round().astype(np.int64))
    col_med = np.median(np.concatenate(list(rows(sample))), axis=0)
    ok = usable[::-1] if flip else np.asarray(usable, bool)
    col_med = col_med[::-1] if flip else col_med
    band = _Band(lo, width, nm, 2 * exclude + 2)
    pen = STEP_COST * np.abs(np.arange(MAX_STEP + 1) - 1.0)
    half = max(window, 1) // 2
    buf: list[np.ndarray] = []  # the rows the next sequence score reads
    acc = np.zeros(width)
    i = 0
    for block in rows(np.arange(nq)):
        for r in block[:, ::-1] if flip else block:
            cols = band.cols(i)
            scale = np.sqrt(max(float(np.median(r[ok])) if ok.any() else 1.0, 1e-12)
                            * np.maximum(col_med[cols], 1e-12))  # fmt: skip
            c = np.minimum(r[cols] / scale, CAP)
            c[~ok[cols]] = CAP
            band.cost[i] = c
            if i:
                k_prev = (
                    np.arange(width)[None, :] - np.arange(MAX_STEP + 1)[:, None] + band.shift(i)
                )
                inside = (k_prev >= 0) & (k_prev < width)
                cand = np.where(inside, acc[np.clip(k_prev, 0, width - 1)], np.inf) + pen[:, None]
                crossing = (cols[None, :] - np.arange(MAX_STEP + 1)[:, None]) < 0
                cand = cand + np.where(crossing, WRAP * CAP, 0.0)
                band.back[i] = np.argmin(cand, axis=0)  # the first least: the smallest step
                acc = cand.min(axis=0) + c
            else:
                acc = c.copy()
            buf.append(np.where(ok, r, np.inf))  # along the path's direction, as path_pairs
            if i >= half:  # row i - half has every neighbour it reads
                u = i - half
                first = max(0, u - half)
                got = _row_scores(np.stack(buf[first - (i + 1 - len(buf)) :]), u - first, window)
                band.scored(u, got)
            if len(buf) > 2 * half + 1:
                buf.pop(0)
            i += 1
    for u in range(max(0, nq - half), nq):  # the run's last rows: the end is their neighbour
        first = max(0, u - half)
        start = nq - len(buf)
        got = _row_scores(np.stack(buf[first - start :]), u - first, window)
        band.scored(u, got)
    k = int(np.argmin(acc))
    at = np.empty(nq, np.int64)
    for i in range(nq - 1, -1, -1):
        at[i] = k
        if i:
            k = k - int(band.back[i, k]) + band.shift(i)
    col = (lo + at) % nm
    idx = np.arange(nq)
    top_j = nm - 1 - band.top_j if flip else band.top_j
    cost = band.cost[idx, at]
    score = band.seq[idx, at].astype(np.float64)
    col = nm - 1 - col if flip else col
    second = np.where(np.abs(top_j - col[:, None]) > exclude, band.top_v, np.inf).min(axis=1)
    return col, score, second, _unpaired(col, cost, np.asarray(usable, bool))


def _unpaired(col: np.ndarray, cost: np.ndarray, usable: np.ndarray) -> dict[int, str]:
    """The query frames a path leaves unpaired, with why (:data:`UNPAIRED_DARK`, ``_WEAK``)."""
    unpaired = {int(i): UNPAIRED_DARK for i in np.flatnonzero(~usable[col])}
    held = np.bincount(col, minlength=len(usable))[col]
    for i in np.flatnonzero((held > STOP_FRAMES) & (cost >= WEAK * CAP) & usable[col]):
        unpaired[int(i)] = UNPAIRED_WEAK
    return unpaired

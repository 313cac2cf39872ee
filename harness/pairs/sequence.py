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

Memory: the path's back-pointers take one byte a cell (``n_query x n_map``), the distances are
streamed a row at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    dist: np.ndarray, seq: np.ndarray, usable: np.ndarray, exclude: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, str]]:
    """Each query frame's map frame on the path, its evidence and rival, and who stays unpaired.

    ``dist``: the (n_q, n_m) frame distances; ``seq``: SeqSLAM's sequence scores of the same cells
    (the evidence), the rival the best of them more than ``exclude`` frames from the path's map
    frame. Returns the path's map frames (positions), the scores there, the rivals, and the query
    frames (positions) left unpaired with why (:data:`UNPAIRED_DARK`, :data:`UNPAIRED_WEAK`).
    """
    col = align(dist, usable).column
    rows = np.arange(len(col))
    pos = np.arange(dist.shape[1])
    rival = np.where(np.abs(pos[None, :] - col[:, None]) > exclude, seq, np.inf)
    second = rival.min(axis=1) if rival.shape[1] else np.full(len(col), np.inf)
    unpaired = {int(i): UNPAIRED_DARK for i in np.flatnonzero(~usable[col])}
    cost = cell_costs(dist, usable, CAP)[rows, col]
    held = np.bincount(col, minlength=dist.shape[1])[col]
    for i in np.flatnonzero((held > STOP_FRAMES) & (cost >= WEAK * CAP) & usable[col]):
        unpaired[int(i)] = UNPAIRED_WEAK
    return col, seq[rows, col], second, unpaired

"""The rank engine's exact re-measurement (method §6), by differences, never the expansion.

A query's distance to its place, and to the frames the product put too close to call.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from harness.retrieval.distances import scratch

log = logging.getLogger(__name__)
#: (query, row) pairs per block of the exact float64 measurement of ``d``.
EXACT_BLOCK = 16
#: (query, row) pairs per call when whole frames are measured exactly (bf16's undecided frames).
EXACT_PAIRS_PER_CALL = 1 << 16
#: float64 values per block when whole frames are measured (many rows per numpy call: the
#: per-call overhead, not the arithmetic, bounds small blocks).
FRAME_BLOCK_VALUES = 1 << 17
#: Queries per block when bf16's per-frame minima are decided (a (block, L) float64 temporary).
RANK_ROWS = 256


@dataclass(frozen=True)
class FrameMeasure:
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


def exact_ranks(
    fm: torch.Tensor,
    qi: np.ndarray,
    pc: np.ndarray,
    exact: ExactPlace,
    fmax: np.ndarray,
    measure: FrameMeasure,
    stats: dict[str, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Rank and L from the product's per-frame minima ``fm``, decided against the exact ``d``.

    A frame F outside the place is within ``E = c (|q| + max |b in F|)^2`` of its true minimum
    (``c``: :func:`expansion_error_factor` or :func:`bf16_error_factor`): it counts when
    ``fm + E < d^2``, not when ``fm - E > d^2``, and is measured exactly (:class:`FrameMeasure`)
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


class ExactPlace:
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

"""101-point interpolated average precision (method §9) and its relatives.

Its size-stratified form (section 8), weighted AP for pixel regions, PR curves, and bootstrap
intervals with paired comparisons.
"""

from __future__ import annotations

import math

import numpy as np

RECALL_GRID = np.linspace(0.0, 1.0, 101)


def pr_curve(labels: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision and recall at every distinct score, descending (tied samples enter together).

    Returns:
        (thresholds, precision, recall), one entry per distinct score value.
    """
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, np.float64)
    order = np.argsort(-scores, kind="stable")
    s, y = scores[order], labels[order]
    last = (
        np.concatenate([np.nonzero(s[1:] != s[:-1])[0], [len(s) - 1]])
        if len(s)
        else np.zeros(0, np.int64)
    )
    tp = np.cumsum(y)[last]
    fp = np.cumsum(~y)[last]
    npos = int(labels.sum())
    precision = tp / np.maximum(tp + fp, 1)
    recall = tp / npos if npos else np.zeros(len(tp))
    return s[last], precision, recall


def _interp_ap(precision: np.ndarray, recall: np.ndarray) -> float:
    """Mean over R = 0, 0.01, ..., 1 of the largest precision at recall >= R (0 if none)."""
    pmax = np.maximum.accumulate(precision[::-1])[::-1]
    idx = np.searchsorted(recall, RECALL_GRID - 1e-12, side="left")
    interp = np.where(idx < len(recall), pmax[np.minimum(idx, len(recall) - 1)], 0.0)
    return float(interp.mean())


def _interp_ap_rows(tp: np.ndarray, fp: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """:func:`_interp_ap` of every row of cumulative (B, m) true/false positive weights at once.

    Row b's precision is ``tp / (tp + fp)`` (0 where both are 0) and its recall ``tp / pos[b]``,
    nondecreasing along the row; NaN where ``pos[b]`` is 0. The rows are laid end to end with
    row b's recall shifted by ``2 b`` (recall lies in [0, 1], so the whole stays sorted), and one
    ``searchsorted`` finds every row's first recall >= R for every R of the grid: the loop of
    :func:`_interp_ap` over rows without a Python step per row.
    """
    B, m = tp.shape
    out = np.full(B, np.nan)
    ok = pos > 0
    if m == 0 or not ok.any():
        return out
    tp, fp, p = tp[ok], fp[ok], pos[ok]
    n = len(p)
    tot = tp + fp
    prec = np.divide(tp, tot, out=np.zeros_like(tot), where=tot > 0)
    pmax = np.maximum.accumulate(prec[:, ::-1], axis=1)[:, ::-1]
    shift = 2.0 * np.arange(n)[:, None]
    keys = (tp / p[:, None] + shift).ravel()
    grid = (RECALL_GRID[None, :] - 1e-12 + shift).ravel()
    idx = np.searchsorted(keys, grid, side="left").reshape(n, -1)
    local = idx - (np.arange(n) * m)[:, None]
    found = local < m
    interp = np.where(found, pmax.ravel()[np.minimum(idx, n * m - 1)], 0.0)
    out[ok] = interp.mean(axis=1)
    return out


def weighted_average_precision(
    labels: np.ndarray, scores: np.ndarray, weights: np.ndarray
) -> float:
    """101-point AP where sample i counts ``weights[i]`` times.

    Weights are pixel areas or bootstrap multiplicities.

    With integer weights it equals :func:`average_precision` of the samples repeated that often.
    NaN when the positives' total weight is 0.
    """
    labels = np.asarray(labels).astype(bool)
    w = np.asarray(weights, np.float64)
    if not (w * labels).sum() > 0:
        return float("nan")
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    s, y, w = np.asarray(scores, np.float64)[order], labels[order], w[order]
    last = np.concatenate([np.nonzero(s[1:] != s[:-1])[0], [len(s) - 1]])
    tp = np.cumsum(w * y)[last]
    fp = np.cumsum(w * ~y)[last]
    keep = (tp + fp) > 0
    tp, fp = tp[keep], fp[keep]
    return _interp_ap(tp / (tp + fp), tp / tp[-1])


def stratified_ap(
    labels: np.ndarray,
    scores: np.ndarray,
    sob: np.ndarray,
    edges: np.ndarray | list[float],
    weights: np.ndarray | None = None,
) -> tuple[float, float]:
    """Size-stratified AP (method §8): (AP, weighted positive rate).

    Samples are binned by SoB into strata ``[edges[k], edges[k+1])`` (the last one closed). Within
    every stratum holding at least one positive and one negative the 101-point AP is computed;
    the result is the mean of those APs weighted by each stratum's positives, and the second
    value the same weighted mean of the strata's positive rates. That is *not* the floor (random
    orders score higher; :func:`harness.evaluate.chance.stratified_chance` measures the floor).
    Strata without a positive or without a negative take no part. (NaN, NaN) when no stratum
    qualifies. ``weights`` (optional) count sample i that many times (bootstrap multiplicities).
    """
    labels = np.asarray(labels).astype(bool)
    wt = np.ones(len(labels)) if weights is None else np.asarray(weights, np.float64)
    scores = np.asarray(scores, np.float64)
    sob = np.asarray(sob, np.float64)
    edges = np.asarray(edges, np.float64)
    k = np.clip(np.searchsorted(edges, sob, side="right") - 1, 0, len(edges) - 2)
    inside = (sob >= edges[0]) & (sob <= edges[-1])
    aps, floors, wts = [], [], []
    for j in range(len(edges) - 1):
        sel = inside & (k == j) & (wt > 0)
        pos, total = float(wt[sel & labels].sum()), float(wt[sel].sum())
        if pos == 0 or pos == total:
            continue
        aps.append(
            weighted_average_precision(labels[sel], scores[sel], wt[sel])
            if weights is not None
            else average_precision(labels[sel], scores[sel])
        )
        floors.append(pos / total)
        wts.append(pos)
    if not wts:
        return float("nan"), float("nan")
    w = np.asarray(wts, np.float64)
    return float(np.dot(w, aps) / w.sum()), float(np.dot(w, floors) / w.sum())


def average_precision(labels: np.ndarray, scores: np.ndarray) -> float:
    """101-point interpolated AP; NaN when there is no positive.

    Samples are sorted by score, descending; precision and recall are taken at every distinct
    score; ``p(R) = max precision over points with recall >= R`` (0 if none); AP is the mean of
    ``p(R)`` over R = 0.00, 0.01, ..., 1.00. Recall is compared with a 1e-12 tolerance so that,
    e.g., 29/100 counts as reaching R = 0.29.
    """
    labels = np.asarray(labels).astype(bool)
    if labels.sum() == 0:
        return float("nan")
    _, p, rec = pr_curve(labels, scores)
    return _interp_ap(p, rec)


def resample_counts(n_groups: int, n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, n_groups) multiplicities of each group in ``n_boot`` resamples with replacement.

    Drawing them once and giving the same matrix to every method makes the bootstrap *paired*:
    each method is scored on the same resampled query images.
    """
    rng = np.random.default_rng(seed)
    out = np.zeros((max(n_boot, 0), n_groups), np.int64)
    for b in range(max(n_boot, 0)):
        out[b] = (
            np.bincount(rng.integers(0, n_groups, n_groups), minlength=n_groups)
            if n_groups
            else out[b]
        )
    return out


class _Ranked:
    """Samples sorted once by score (descending, stable) with the ends of tied groups.

    The AP of any reweighting (a bootstrap resample) then costs one cumulative sum, not a sort.
    """

    def __init__(self, labels: np.ndarray, scores: np.ndarray, members: np.ndarray) -> None:
        s = np.asarray(scores, np.float64)[members]
        order = np.argsort(-s, kind="stable")
        self.idx = members[order]
        self.y = np.asarray(labels, bool)[self.idx]
        ss = s[order]
        self.last = (
            np.concatenate([np.nonzero(ss[1:] != ss[:-1])[0], [len(ss) - 1]])
            if len(ss)
            else np.zeros(0, np.int64)
        )

    def aps(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(AP, positive weight) for each row of ``w`` ((B, n_samples) weights of all samples)."""
        ws = w[:, self.idx]
        tp = np.cumsum(ws * self.y, axis=1)[:, self.last]
        fp = np.cumsum(ws * ~self.y, axis=1)[:, self.last]
        pos = tp[:, -1] if tp.shape[1] else np.zeros(len(w))
        return _interp_ap_rows(tp, fp, pos), pos


def bootstrap_aps(
    labels: np.ndarray,
    scores: np.ndarray,
    group_index: np.ndarray,
    counts: np.ndarray,
    weights: np.ndarray | None = None,
    strata: tuple[np.ndarray, np.ndarray] | None = None,
    block_bytes: int = 64 << 20,
) -> np.ndarray:
    """AP (or stratified AP) of every resample; ``counts`` from :func:`resample_counts`.

    The samples are sorted once; each resample is a reweighting (a sample drawn k times counts k
    times), evaluated in blocks of resamples whose weight matrix stays under ``block_bytes``.
    Equal to :func:`weighted_average_precision` / :func:`stratified_ap` of each resample.

    Args:
        labels: (n,) bool, the positives.
        scores: (n,) LoC, higher = more likely changed.
        group_index: (n,) the query image (0..n_groups-1) of each sample.
        weights: optional per-sample weights (pixel areas), multiplied by the group's multiplicity.
        counts: (n_boot, n_groups) multiplicity of each query image in each resample.
        strata: (sob, edges): the stratified AP (:func:`stratified_ap`) of the samples' SoB
            ``sob`` (n,) in the strata of ``edges``; None: the plain AP.
        block_bytes: the largest weight matrix evaluated at once, bytes.

    Returns:
        (n_boot,) APs; NaN where a resample has no positive.
    """
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, np.float64)
    n = len(labels)
    base = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    if strata is not None:
        sb, e = np.asarray(strata[0], np.float64), np.asarray(strata[1], np.float64)
        k = np.clip(np.searchsorted(e, sb, side="right") - 1, 0, len(e) - 2)
        inside = (sb >= e[0]) & (sb <= e[-1])
        parts = [
            _Ranked(labels, scores, np.nonzero(inside & (k == j))[0]) for j in range(len(e) - 1)
        ]
    else:
        parts = [_Ranked(labels, scores, np.arange(n))]
    out = np.empty(len(counts))
    step = max(1, int(block_bytes // max(8 * n, 1)))
    for b0 in range(0, len(counts), step):
        w = base[None, :] * counts[b0 : b0 + step][:, group_index]
        if strata is None:
            out[b0 : b0 + step] = parts[0].aps(w)[0]
            continue
        num = np.zeros(len(w))
        den = np.zeros(len(w))
        for part in parts:
            if not len(part.idx):
                continue
            ap, pos = part.aps(w)
            total = w[:, part.idx].sum(1)
            ok = (pos > 0) & (pos < total)  # a stratum takes part with a positive and a negative
            num[ok] += pos[ok] * ap[ok]
            den[ok] += pos[ok]
        out[b0 : b0 + step] = np.divide(num, den, out=np.full(len(w), np.nan), where=den > 0)
    return out


def interval(values: np.ndarray, ci: float) -> tuple[float, float]:
    """Percentile interval at level ``ci`` of the finite values (NaN, NaN if none)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return float("nan"), float("nan")
    a = (1 - ci) / 2
    return float(np.quantile(v, a)), float(np.quantile(v, 1 - a))


def paired_difference(
    aps_a: np.ndarray, aps_b: np.ndarray, ap_a: float, ap_b: float, ci: float
) -> dict[str, float]:
    """``a - b`` from a paired bootstrap.

    The difference, its interval, the share of resamples whose difference has the other sign
    than the observed one (NaN when the observed one is 0), and its two-sided p-value from the
    bootstrap standard error, ``erfc(|diff| / (sd sqrt 2))`` (the normal approximation; 1 when the
    difference is 0, NaN without resamples), which :func:`holm` corrects for multiplicity. A
    count of sign flips could not go below ``2 / (B + 1)``, too coarse for a correction over
    dozens of differences at B = 1000.
    """
    d = np.asarray(aps_a, np.float64) - np.asarray(aps_b, np.float64)
    d = d[np.isfinite(d)]
    diff = ap_a - ap_b
    lo, hi = interval(d, ci)
    nan = float("nan")
    flips = float(np.mean(np.sign(d) != np.sign(diff))) if len(d) and diff != 0 else nan
    p = nan
    if len(d) > 1 and diff == diff:
        sd = float(np.std(d, ddof=1))
        if diff == 0:
            p = 1.0
        elif sd > 0:
            p = float(math.erfc(abs(diff) / (sd * math.sqrt(2.0))))
        else:
            p = 0.0  # every resample gives the same nonzero difference
    return {
        "diff": diff,
        "diff_ci_low": lo,
        "diff_ci_high": hi,
        "sign_flip_share": flips,
        "p_value": p,
    }


def holm(p: np.ndarray, alpha: float) -> np.ndarray:
    """Holm's step-down correction: which of the p-values (NaN: not tested) survive at ``alpha``.

    Sorted ascending, the i-th smallest of m tested p-values is rejected while every p-value up
    to it is at most ``alpha / (m - j)`` (j = 0, 1, ...); the family-wise error rate is at most
    ``alpha`` whatever the dependence between the tests.
    """
    p = np.asarray(p, np.float64)
    out = np.zeros(len(p), bool)
    idx = np.flatnonzero(np.isfinite(p))
    m = len(idx)
    for j, i in enumerate(idx[np.argsort(p[idx], kind="stable")]):
        if p[i] > alpha / (m - j):
            break
        out[i] = True
    return out

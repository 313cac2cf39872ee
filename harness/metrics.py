"""101-point interpolated average precision (SPEC section 9), PR curves and bootstrap intervals."""

from __future__ import annotations

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
    last = np.concatenate([np.nonzero(s[1:] != s[:-1])[0], [len(s) - 1]]) if len(s) else np.zeros(0, np.int64)
    tp = np.cumsum(y)[last]
    fp = np.cumsum(~y)[last]
    npos = int(labels.sum())
    precision = tp / np.maximum(tp + fp, 1)
    recall = tp / npos if npos else np.zeros(len(tp))
    return s[last], precision, recall


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
    # suffix max of precision over recall-sorted points (recall is non-decreasing along the curve)
    pmax = np.maximum.accumulate(p[::-1])[::-1]
    idx = np.searchsorted(rec, RECALL_GRID - 1e-12, side="left")
    interp = np.where(idx < len(rec), pmax[np.minimum(idx, len(rec) - 1)], 0.0)
    return float(interp.mean())


def bootstrap_ap(
    labels: np.ndarray, scores: np.ndarray, groups: np.ndarray, n_boot: int, ci: float, seed: int
) -> tuple[float, float]:
    """Percentile interval of AP when whole groups (query images) are resampled with replacement.

    Returns (low, high); NaN when no resample has a positive or ``n_boot`` is 0.
    """
    if n_boot <= 0 or len(labels) == 0:
        return float("nan"), float("nan")
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, np.float64)
    uniq, inv = np.unique(groups, return_inverse=True)
    members = [np.nonzero(inv == g)[0] for g in range(len(uniq))]
    rng = np.random.default_rng(seed)
    aps = []
    for _ in range(n_boot):
        pick = rng.integers(0, len(uniq), len(uniq))
        idx = np.concatenate([members[g] for g in pick])
        aps.append(average_precision(labels[idx], scores[idx]))
    aps_arr = np.array(aps)
    aps_arr = aps_arr[~np.isnan(aps_arr)]
    if not len(aps_arr):
        return float("nan"), float("nan")
    a = (1 - ci) / 2
    return float(np.quantile(aps_arr, a)), float(np.quantile(aps_arr, 1 - a))

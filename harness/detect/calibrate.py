"""Scores a robot can threshold (SPEC 13.1): each raw LoC as an exceedance against a null.

Raw LoC (``N * sum 1/r'``) has no unit. The calibrated score of a box is the share of the run's
candidate boxes (every box the generator proposed on every query frame, changes being rare) that
score at least as high; of a frame, the share of the run's frames whose change score is at least
its own. Both are estimated without annotations, as ``(1 + #{null >= s}) / (1 + n)``, which never
reaches 0 and is a valid (conservative) p-value under the null that the score is drawn like the
others. Thresholding it at a rate ``a`` (``harness detect --alarm a``) flags about a share ``a``
of unchanged content: the nominal false-alarm rate. Changed content in the null only makes the
flagged share smaller, so the measured rate on frames annotated ``no-change`` (Table D) should be
at most the nominal one.
"""

from __future__ import annotations

import numpy as np


def exceedance(null: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``(1 + #{null >= v}) / (1 + n)`` for each ``v`` of ``values`` (NaN stays NaN).

    ``null``'s non-finite values are left out; with an empty null every value gets 1.
    """
    ref = np.sort(np.asarray(null, np.float64)[np.isfinite(np.asarray(null, np.float64))])
    v = np.asarray(values, np.float64)
    ge = len(ref) - np.searchsorted(ref, v, side="left")
    out = (1.0 + ge) / (1.0 + len(ref))
    return np.where(np.isfinite(v), out, np.nan)


def in_words(p: float, what: str) -> str:
    """``1 in 1,000 {what} scores this high`` (the exceedance as a person reads it).

    From a share of one in five up, where "1 in n" reads oddly ("1 in 1 frames"), the share
    itself: ``60% of {what} score this high``.
    """
    if p != p:
        return f"no calibrated score ({what})"
    if p > 0.2:
        return f"{100 * p:.0f}% of {what} score this high"
    n = max(1, round(1.0 / p))
    return f"1 in {n:,} {what} scores this high"

"""Score sum (method §7): the sum of the covering originals' relevance scores ``d``."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import rule


@rule("score_sum")
def score_sum(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The sum of the covering originals' relevance scores ``d``."""
    return np.asarray((cover * d[None, :]).sum(1), np.float64)

"""Score max (method §7): the largest relevance score ``d`` of the covering originals."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import rule


@rule("score_max")
def score_max(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The largest relevance score ``d`` of the covering originals."""
    return np.asarray(np.where(cover, d[None, :], -np.inf).max(1))

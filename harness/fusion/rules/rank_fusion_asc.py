"""The paper's variant 2 of rank fusion, ascending order: ``1 / (N * sum(1/r))``."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import rule


@rule("rank_fusion_asc")
def rank_fusion_asc(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The paper's variant 2, ascending order (an earlier formula): ``1 / (N * sum(1/r))``."""
    return np.asarray(1.0 / (cover.sum(1) * (cover * (1.0 / r)[None, :]).sum(1)), np.float64)

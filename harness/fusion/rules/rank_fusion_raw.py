"""The paper's variant 1 of rank fusion: ``1 / (L + 1 - rank)`` in place of ``1 / r'``."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import paper_sum, r_desc_of, rule


@rule("rank_fusion_raw")
def rank_fusion_raw(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The paper's variant 1: ``1 / (L + 1 - rank)`` in place of ``1 / r'``."""
    return paper_sum(cover, 1.0 / (r_desc_of(r, L) * np.asarray(L, np.float64)))

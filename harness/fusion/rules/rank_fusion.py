"""The paper's rank fusion (method §7): ``N * sum(1 / r')`` over the covering originals."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import paper_sum, r_desc_of, rule


@rule("rank_fusion")
def rank_fusion(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The paper's rank fusion: ``N * sum(1 / r')``."""
    return paper_sum(cover, 1.0 / r_desc_of(r, L))

"""RRF, reciprocal rank fusion: ``sum 1 / (c + rank')`` over the covering lists (method §14)."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import FORMULAS, rule, standard


def rrf_formula(
    cov: np.ndarray, n: np.ndarray, rank: np.ndarray, rank_d: np.ndarray, L: np.ndarray, c: float
) -> np.ndarray:
    """Rrf of the covering lists (:func:`harness.fusion.rules.base.standard_rule`)."""
    return np.asarray(cov @ (1.0 / (c + rank_d)), np.float64)


FORMULAS.add("rrf", rrf_formula)
rrf = rule("rrf")(standard("rrf"))

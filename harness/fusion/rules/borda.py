"""Borda count: the mean of ``(rank - 1) / L`` over the covering lists (method §14)."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import FORMULAS, rule, standard


def borda_formula(
    cov: np.ndarray, n: np.ndarray, rank: np.ndarray, rank_d: np.ndarray, L: np.ndarray, c: float
) -> np.ndarray:
    """Borda of the covering lists (:func:`harness.fusion.rules.base.standard_rule`)."""
    return np.asarray((cov @ ((rank - 1.0) / L)) / np.maximum(n, 1.0), np.float64)


FORMULAS.add("borda", borda_formula)
borda = rule("borda")(standard("borda"))

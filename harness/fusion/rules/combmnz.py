"""CombMNZ over rank-normalised scores: ``N * sum(rank / L)`` (method §14)."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import FORMULAS, rule, standard


def combmnz_formula(
    cov: np.ndarray, n: np.ndarray, rank: np.ndarray, rank_d: np.ndarray, L: np.ndarray, c: float
) -> np.ndarray:
    """Combmnz of the covering lists (:func:`harness.fusion.rules.base.standard_rule`)."""
    return np.asarray(n * (cov @ (rank / L)), np.float64)


FORMULAS.add("combmnz", combmnz_formula)
combmnz = rule("combmnz")(standard("combmnz"))

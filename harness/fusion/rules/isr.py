"""ISR, inverse square rank: ``N * sum(1 / rank'^2)`` (method §14)."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import FORMULAS, rule, standard


def isr_formula(
    cov: np.ndarray, n: np.ndarray, rank: np.ndarray, rank_d: np.ndarray, L: np.ndarray, c: float
) -> np.ndarray:
    """Isr of the covering lists (:func:`harness.fusion.rules.base.standard_rule`)."""
    return np.asarray(n * (cov @ (1.0 / rank_d**2)), np.float64)


FORMULAS.add("isr", isr_formula)
isr = rule("isr")(standard("isr"))

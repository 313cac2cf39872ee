"""The random baseline (``random``): uniform in [0, 1), reproducible per image."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import rule


@rule("random")
def random_loc(fused: np.ndarray, width: float, height: float, seed: int) -> np.ndarray:
    """Uniform in [0, 1), reproducible per image (``seed``: the query image's)."""
    return np.random.default_rng(seed).random(len(fused))

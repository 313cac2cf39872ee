"""Size prior: 1 - SoB, a sample's LoC from its size alone (a baseline that reads no pixel)."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import rule


@rule("size_prior")
def size_prior(fused: np.ndarray, width: float, height: float, seed: int) -> np.ndarray:
    """1 - SoB: a sample's LoC from its size alone (the baseline that reads no pixel)."""
    area = (fused[:, 2] - fused[:, 0]) * (fused[:, 3] - fused[:, 1])
    return np.asarray(1.0 - area / float(width * height), np.float64)

"""Cover count: how many originals cover the box, a baseline that reads no pixel (method §7)."""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import rule


@rule("cover_count")
def cover_count(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """How many originals cover the box: a baseline that reads no pixel."""
    return np.asarray(cover.sum(1), np.float64)

"""Rank fusion over at most 2 or 3 covering originals (``rank_fusion_le2``, ``rank_fusion_le3``).

method §7: where more cover the box, a random k of them, per image seed.
"""

from __future__ import annotations

import numpy as np

from harness.fusion.rules.base import Loc, paper_sum, r_desc_of, rule


def subset_cover(cover: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Where a row covers more than k originals, keep a random k of them (in row order)."""
    out = cover.copy()
    for i in np.nonzero(cover.sum(1) > k)[0]:
        idx = np.nonzero(cover[i])[0]
        keep = rng.choice(idx, size=k, replace=False)
        out[i] = False
        out[i, keep] = True
    return out


def _rank_fusion_le(k: int) -> Loc:
    def le(
        cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray, *, seed: int = 0
    ) -> np.ndarray:
        sub = subset_cover(cover, k, np.random.default_rng(seed))
        return paper_sum(sub, 1.0 / r_desc_of(r, L))

    le.__doc__ = f"Rank fusion over at most {k} covering originals (a random {k}, per image seed)."
    return le


rank_fusion_le2 = rule("rank_fusion_le2")(_rank_fusion_le(2))
rank_fusion_le3 = rule("rank_fusion_le3")(_rank_fusion_le(3))

"""A fusion rule with an option: the k-th largest 1/r' among the boxes covering a sample.

A plugin: ``plugins = ["examples/plugins/kth_rank.py"]`` in a config, or ``harness --plugin
examples/plugins/kth_rank.py ...``; then ``[fusion] methods`` may list ``kth_rank`` and
``[fusion.kth_rank]`` set ``k``.
"""

from dataclasses import dataclass

import numpy as np

from harness.fusion import register_fusion_rule


@dataclass(frozen=True)
class KthRank:
    """``[fusion.kth_rank]``."""

    k: int = 2  # which of the covering boxes' 1/r', largest first


def kth_rank(cover, r, d, L, *, options):
    """LoC of each fused box: the ``options.k``-th largest 1/r' of the originals covering it."""
    inv = np.where(cover, (L / (L + 1.0 - r * L))[None, :], 0.0)
    k = min(options.k, cover.shape[1])
    return -np.sort(-inv, axis=1)[:, k - 1]


register_fusion_rule("kth_rank", kth_rank, "k-th best rank", options=KthRank)

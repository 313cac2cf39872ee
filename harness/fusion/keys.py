"""The samples' key: ranks, annotations, ``[fusion]`` and ``[splits]``.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses

from harness.evaluate.config import SplitsConfig
from harness.fusion.config import FusionConfig
from harness.fusion.fuse import rule_fingerprints
from harness.runtime.cache import Parts, without_empty


def samples(fc: FusionConfig, sp: SplitsConfig, ranks_key: str, ann_key: str) -> Parts:
    """Samples: ranks, annotations, ``[fusion]``, ``[splits]`` (and registered methods' source)."""
    return (
        ranks_key,
        ann_key,
        without_empty(dataclasses.asdict(fc), "options"),
        dataclasses.asdict(sp),
        rule_fingerprints(fc.methods),
    )

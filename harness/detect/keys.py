"""The keys of ``harness detect``'s chunks.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from harness.fusion.config import FusionConfig
from harness.fusion.fuse import rule_fingerprints
from harness.methods import FUSION_RULES
from harness.runtime.cache import Parts


def detect_chunk(
    ranks_key: str, record: dict[str, Any], first: int, n: int, fc: FusionConfig, rule: str
) -> Parts:
    """One chunk of ``harness detect``.

    Its ranks, ``[detect]`` (less the chunk size), the chunk's query frames from ``first``, and
    the fusion rule: its source, the ``[fusion]`` values its function takes as keywords (``rrf_c``;
    the seed is ``[detect]``'s) and its own table.
    """
    options = fc.options_of(rule)
    keywords = [o for o in FUSION_RULES[rule].options if o not in ("seed", "options")]
    return (
        "detect",
        ranks_key,
        record | {"chunk_frames": None},
        first,
        n,
        rule_fingerprints((rule,)),
        *(getattr(fc, o) for o in keywords),
        *((dataclasses.asdict(options),) if options is not None else ()),
    )

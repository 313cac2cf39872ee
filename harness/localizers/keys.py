"""The localizers' keys: a local localizer's units and table, the blocks across localizers.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from harness.runtime.cache import Parts, stable_hash


def local_ranks(
    lc: Any, pairs_key: str, proposal_keys: list[str], c0: int, n: int, tag: str = "local"
) -> Parts:
    """A unit of a ``local`` (or ``keypoints``, ``tag``) localizer's ranks.

    Its options (less the unit size), pairs, proposals.
    """
    opts = {k: v for k, v in dataclasses.asdict(lc).items() if k != "frames_per_unit"}
    return ("local_ranks" if tag == "local" else f"{tag}_ranks", opts, pairs_key, proposal_keys,
            c0, n)  # fmt: skip


def local_ranks_table(unit_parts: list[Parts], tag: str = "local") -> str:
    """A ``local`` (or ``keypoints``) localizer's rank table: its units' keys."""
    return stable_hash(tag, *unit_parts)


def common_images(ranks_key: str, dropped: int) -> str:
    """A localizer's ranks cut to the images every localizer ranked (``dropped`` rows less)."""
    return stable_hash("common-images", ranks_key, dropped)


def all_localizers(ranks_keys: list[str]) -> str:
    """The ``all localizers`` block's ranks: every localizer's."""
    return stable_hash("all-localizers", ranks_keys)

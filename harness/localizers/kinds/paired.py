"""A localizer kind that ranks each query box inside its paired map frame, from one function.

``local`` and ``keypoints`` are two; a new one is its options' dataclass (with a
``frames_per_unit`` field: the pairs one cached unit holds) and a function of the options that
returns its pair function (:data:`harness.localizers.local.PairRanks`: the query and map images'
URIs, the query frame's size and its boxes -> the pair's (method, inliers, score) and each box's
(rank, L, 1 - d), NaN where it has none, or None where the pair could not be compared). The
harness does the rest: units, caching, the rank rows, ``harness detect``'s chunks and its no-change
null (docs/architecture.md, *Where to add*).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from harness.localizers import stage as localizer_stage
from harness.localizers.config import LocalizerConfig
from harness.localizers.kinds.base import LocalizerKind, LocalizerRun
from harness.localizers.kinds.local import costs
from harness.localizers.local import PairRanks, unit_ranks
from harness.retrieval.config import RetrievalConfig
from harness.runtime.stage import RankTable, Table

#: The counters every paired kind's units keep (``pairs_<method>`` are added as they come).
COUNTS = ("query_subimages", "ranked", "no_rank_box", "no_rank_pair_not_aligned")


def _write(
    pair_ranks: Callable[[Any], PairRanks],
    opts: Any,
    pairs: pd.DataFrame,
    frames: pd.DataFrame,
    props: pd.DataFrame,
    tmp: Path,
) -> dict[str, int]:
    return unit_ranks(pair_ranks(opts), pairs, frames, props, tmp, COUNTS, "no_rank_box")


def _ranks(
    name: str,
    pair_ranks: Callable[[Any], PairRanks],
    p: LocalizerRun,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    rc: RetrievalConfig,
) -> RankTable:
    del rc  # the place is the paired frame itself
    write = partial(_write, pair_ranks)
    return localizer_stage.paired_frame_ranks(p, loc.options, frames, pairs, mine, write, name)


def paired_frame_kind(
    name: str,
    options: type,
    pair_ranks: Callable[[Any], PairRanks],
    summary: Callable[[dict[str, Any], dict[str, Any]], str] | None = None,
) -> LocalizerKind:
    """The kind ``name`` that ranks each box inside its paired map frame by ``pair_ranks(opts)``.

    Register it with :func:`harness.localizers.kinds.register_localizer_kind`; then ``harness
    detect --localizer NAME`` ranks with it (its options' defaults; a ``[[localizers]]`` entry
    takes them as a sub-table), and its no-change null is scored the same way.
    """
    return LocalizerKind(
        name, options, ranks=partial(_ranks, name, pair_ranks), costs=costs, summary=summary,
        paired_frame=True,
    )  # fmt: skip

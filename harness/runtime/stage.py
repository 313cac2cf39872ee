"""What a stage function takes and gives: the run it builds entries in, and its outputs' records.

A stage function (``harness/<stage>/stage.py``) takes a :class:`Units` (the run:
:class:`harness.pipeline.context.Context`), its config sections and the tables of the stages
before it, and returns its own: an :class:`Entry` (a cache directory and its key), a
:class:`Table` (a table and its entry's key) or a :class:`RankTable`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import pandas as pd

from harness.runtime.cache import StageCache

Build = Callable[[Path], "dict[str, Any] | None"]
#: One shard of a sharded stage: (session, its rows, the shard's frames, a progress label)
#: -> (key parts, build).
ShardUnit = Callable[[str, pd.DataFrame, list[int], str], "tuple[tuple[Any, ...], Build]"]
#: A session's combined entry: (session, its shard entries) -> (key parts, build).
CombineUnit = Callable[[str, "list[Entry]"], "tuple[tuple[Any, ...], Build]"]


@dataclass(frozen=True)
class Entry:
    """A finished cache entry: its directory and its key."""

    path: Path
    key: str


@dataclass(frozen=True)
class Table:
    """A stage's table (read from its cache entry) and the entry's key."""

    df: pd.DataFrame
    key: str


@dataclass(frozen=True)
class RankTable:
    """Rank rows of every query subimage, their key, and counters per reference session."""

    df: pd.DataFrame
    key: str
    counts: dict[str, dict[str, int]]
    #: The ``local`` kind's alignment of each pair (method, inliers, score); None for others.
    alignment: pd.DataFrame | None = None


class Units(Protocol):
    """The run a stage function builds its entries in (:class:`harness.pipeline.context.Context`).

    Attributes:
        out: The run directory.
        cache: The run's stage cache (a finished entry's manifest).
    """

    out: Path
    cache: StageCache

    def unit(self, stage: str, key_parts: tuple[Any, ...], build: Build) -> Entry:
        """The entry of ``stage`` for ``key_parts``, built by ``build(tmp)`` unless cached."""
        ...

    def units(
        self, stage: str, units: list[tuple[tuple[Any, ...], Build]], gpu: bool = False
    ) -> list[Entry]:
        """Entries of independent units of ``stage``, built through the run's executor."""
        ...

    def sharded(self, stages: tuple[str, str], props: dict[str, Table], shard_frames: int,
                shard: ShardUnit, combine: CombineUnit, gpu: bool = False,
                ) -> tuple[dict[str, Entry], list[Entry]]:  # fmt: skip
        """Shard, build, combine: a per-session stage cached in shards of frames."""
        ...

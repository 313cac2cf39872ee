"""Kind ``local``: each subimage ranked inside its paired map frame (SPEC 13.3)."""

from __future__ import annotations

from pathlib import Path

from harness.localizers import stage as localizer_stage
from harness.localizers.config import LocalConfig, LocalizerConfig, check_local
from harness.localizers.kinds.base import LocalizerKind, LocalizerRun
from harness.retrieval.config import RetrievalConfig
from harness.runtime.stage import RankTable, Table


def prepare(lc: LocalConfig, where: str, base: Path, root: Path) -> LocalConfig:
    """The ``local`` table checked at load."""
    return check_local(lc, f"{where}.local")


def ranks(
    p: LocalizerRun,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    rc: RetrievalConfig,
) -> RankTable:
    """Units of ``frames_per_unit`` pairs, each writing its rank rows and its pairs' alignments.

    ``rc`` does not enter: the place is the paired frame itself.
    """
    del rc
    return localizer_stage.local_ranks(p, loc.options, frames, pairs, mine)


KIND = LocalizerKind("local", LocalConfig, prepare, ranks=ranks)

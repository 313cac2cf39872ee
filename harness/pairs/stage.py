"""The pairs stage (SPEC 4, 13.2): each query frame's map frame by pose or by name or order.

Pairing by retrieval and by sequence ranks candidates (:func:`candidate_table`) with a
localizer's descriptors: that stage is :func:`harness.retrieval.stage.retrieval_pair_table`.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path

import pandas as pd

from harness.errors import ConfigError
from harness.ingest.config import SessionConfig
from harness.ingest.names import session_names
from harness.pairs import keys as pair_keys
from harness.pairs.build import DECLARED, candidate_pairs, write_pairs
from harness.pairs.config import PairsConfig
from harness.runtime.cache import read_cached_parquet
from harness.runtime.stage import Table, Units


def query_pairs(
    p: Units,
    pc: PairsConfig,
    sessions: Sequence[SessionConfig],
    seasons: dict[str, str],
    frames: Table,
    ann: Table,
) -> Table:
    """Frames (+ annotations) -> a reference viewpoint per query frame and season (SPEC 4)."""
    queries = ann.df if pc.queries == "annotated" else None
    build = partial(_write_pairs, frames.df, pc, sessions, seasons, queries)
    entry = p.unit("pairs", pair_keys.pairs(pc, seasons, frames.key, ann.key), build)
    return Table(read_cached_parquet(entry.path / "pairs.parquet"), entry.key)


def _write_pairs(
    frames: pd.DataFrame,
    pc: PairsConfig,
    sessions: Sequence[SessionConfig],
    seasons: dict[str, str],
    queries: pd.DataFrame | None,
    tmp: Path,
) -> dict:
    """The pairs stage's build.

    The folder sessions' file names are read only where pairs need them (``[pairs] by =
    "name"`` or ``"order"``).
    """
    names = session_names(sessions) if pc.by in DECLARED else None
    if pc.by == "name" and names is not None and not len(names):
        raise ConfigError(
            "[pairs] by = 'name' pairs images by their file names, and no session is a folder "
            "of images (logs have no file names): use by = 'order', 'sequence' or 'retrieval'"
        )
    return write_pairs(frames, pc, seasons, queries, names, tmp)


def candidate_table(pc: PairsConfig, seasons: dict[str, str], frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> query frames and the sessions to pair them with (SPEC 13.2).

    ``[pairs] by = "retrieval"``: the frame each is paired with comes later, from the
    localizer's descriptors (:func:`harness.retrieval.stage.retrieval_pair_table`).
    """
    queries = ann.df if pc.queries == "annotated" else None
    cand = candidate_pairs(frames.df, seasons, queries)
    return Table(cand, pair_keys.candidates(pc, seasons, frames.key, ann.key))

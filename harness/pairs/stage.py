"""The pairs stages (method §4, 13.2): each query frame's map frame, by any pairing mode.

One module per mode: by pose (:mod:`.pose`), by name or order (:mod:`.declared`), by retrieval or
sequence (:mod:`.retrieval`: candidates (:func:`candidate_table`) ranked with a localizer's
descriptors, :func:`retrieval_pair_table`); the pair table's shape is :mod:`.table`, the keys
:mod:`.keys`.
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
from harness.pairs.config import PairsConfig
from harness.pairs.modes import PAIRING_MODES, kind_of
from harness.pairs.retrieval import candidate_pairs, write_retrieval_pairs
from harness.runtime.cache import read_cached_parquet, write_json, write_parquet
from harness.runtime.stage import Entry, Table, Units


def query_pairs(
    p: Units,
    pc: PairsConfig,
    sessions: Sequence[SessionConfig],
    seasons: dict[str, str],
    frames: Table,
    ann: Table,
) -> Table:
    """Frames (+ annotations) -> a reference viewpoint per query frame and season (method §4)."""
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
    names = session_names(sessions) if kind_of(pc.by) == "declared" else None
    if pc.by == "name" and names is not None and not len(names):
        raise ConfigError(
            "[pairs] by = 'name' pairs images by their file names, and no session is a folder "
            "of images (logs have no file names): use by = 'order', 'sequence' or 'retrieval'"
        )
    return write_pairs(frames, pc, seasons, queries, names, tmp)


def candidate_table(pc: PairsConfig, seasons: dict[str, str], frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> query frames and the sessions to pair them with (method §13.2).

    ``[pairs] by = "retrieval"``: the frame each is paired with comes later, from the
    localizer's descriptors (:func:`harness.retrieval.stage.retrieval_pair_table`).
    """
    queries = ann.df if pc.queries == "annotated" else None
    cand = candidate_pairs(frames.df, seasons, queries)
    return Table(cand, pair_keys.candidates(pc, seasons, frames.key, ann.key))


def write_pairs(
    frames: pd.DataFrame,
    cfg: PairsConfig,
    seasons: dict[str, str],
    queries: pd.DataFrame | None,
    names: pd.DataFrame | None,
    tmp: Path,
) -> dict:
    """Build the pairs into ``tmp/pairs.parquet`` and ``tmp/summary.json``.

    By the build of the mode ``[pairs] by`` names: by pose (:func:`.pose.build_pairs`), or by
    name or order (:func:`.declared.declared_pairs`, with the frames' ``names``).

    Returns:
        The pairing summary (queries, pairs, drops by reason).
    """
    build = PAIRING_MODES[cfg.by].build
    if build is None:
        raise ValueError(f"[pairs] by = {cfg.by!r}: its pairs need the localizer's descriptors")
    pairs, summary = build(frames, cfg, seasons, queries, names)
    write_parquet(tmp / "pairs.parquet", pairs)
    write_json(tmp / "summary.json", summary)
    return summary


def retrieval_pair_table(
    p: Units,
    pc: PairsConfig,
    memory_mb: float,
    frames: Table,
    cand: Table,
    described: dict[str, Entry],
    proposer: str,
) -> Table:
    """Candidates + descriptors -> each query frame's map frame by retrieval (method §13.2).

    ``memory_mb``: ``[retrieval] memory_mb``; ``proposer``: the one whose descriptors rank.
    """
    paths = {s: e.path for s, e in described.items()}
    options = {
        "memory_mb": memory_mb,
        "place_frames": pc.place_frames,
        "window": pc.sequence_frames if PAIRING_MODES[pc.by].sequence else 0,
        "min_place_contrast": pc.min_place_contrast,
    }
    build = partial(write_retrieval_pairs, cand.df, paths, frames.df, proposer, options)
    dkeys = {s: e.key for s, e in described.items()}
    key = (*pair_keys.by_retrieval(cand.key, dkeys, proposer), pc.min_place_contrast)
    entry = p.unit("pairs_retrieval", key, build)
    return Table(read_cached_parquet(entry.path / "pairs.parquet"), entry.key)

"""The ``local`` localizer's stage (method §13.3): each subimage ranked inside its paired map frame.

Its key is made in :mod:`harness.localizers.keys`; a unit is
:func:`harness.localizers.local.write_local_ranks`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import pandas as pd

from harness.localizers import keys as localizer_keys
from harness.localizers.config import KeypointConfig, LocalConfig
from harness.localizers.keypoints import write_keypoint_ranks
from harness.localizers.local import write_local_ranks
from harness.records import QUERY_KEY
from harness.retrieval.stage import concat_ranks
from harness.runtime.cache import read_cached_parquet
from harness.runtime.stage import Build, RankTable, Table, Units


def local_ranks(
    p: Units, lc: LocalConfig, frames: Table, pairs: Table, mine: dict[str, Table]
) -> RankTable:
    """Pairs + proposals -> each query subimage's rank inside its paired map frame.

    Units of ``frames_per_unit`` pairs; each writes its rank rows and its pairs' alignments.
    """
    return paired_frame_ranks(p, lc, frames, pairs, mine, write_local_ranks, "local")


def keypoint_ranks(
    p: Units, kc: KeypointConfig, frames: Table, pairs: Table, mine: dict[str, Table]
) -> RankTable:
    """Pairs + proposals -> each query subimage's share of keypoints that do not localize.

    In its paired map frame, as a rank (:mod:`harness.localizers.keypoints`); units as
    :func:`local_ranks`.
    """
    return paired_frame_ranks(p, kc, frames, pairs, mine, write_keypoint_ranks, "keypoints")


def paired_frame_ranks(
    p: Units,
    opts: Any,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    write: Callable[..., dict[str, int]],
    tag: str,
) -> RankTable:
    """The units of a kind that ranks each query box inside its paired map frame.

    ``write`` (options, pairs, frames, proposals, tmp) builds each; ``tag`` names the kind (its
    keys and counters).
    """
    qs = sorted(set(pairs.df["q_session"]))
    props = pd.concat([mine[s].df for s in qs], ignore_index=True) if qs else pd.DataFrame()
    pkeys = [mine[s].key for s in qs]
    step = max(1, opts.frames_per_unit)
    units: list[tuple[tuple[Any, ...], Build]] = []
    for c0 in range(0, len(pairs.df), step):
        chunk = pairs.df.iloc[c0 : c0 + step].reset_index(drop=True)
        sel = props.merge(
            chunk[QUERY_KEY].rename(
                columns={"q_session": "session", "q_camera": "camera", "q_utime": "utime"}
            ),
            on=["session", "camera", "utime"],
        )
        build = partial(write, opts, chunk, frames.df, sel)
        parts_key = localizer_keys.local_ranks(opts, pairs.key, pkeys, c0, len(chunk), tag)
        units.append((parts_key, build))
    parts, aligns = [], []
    counts: dict[str, int] = {}
    for entry in p.units("ranks", units):
        parts.append(read_cached_parquet(entry.path / "ranks.parquet"))
        aligns.append(read_cached_parquet(entry.path / "alignment.parquet"))
        for k, v in p.cache.manifest("ranks", entry.key)["info"].items():
            counts[k] = counts.get(k, 0) + v
    alignment = pd.concat(aligns, ignore_index=True) if aligns else pd.DataFrame()
    key = localizer_keys.local_ranks_table([u[0] for u in units], tag)
    return RankTable(concat_ranks(parts), key, {tag: counts}, alignment)

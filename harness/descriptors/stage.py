"""The descriptor stages (method §6): the model, the projection, each session's descriptors.

Their keys are made in :mod:`harness.descriptors.keys`; the builds are in
:mod:`harness.descriptors.extract`.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import pandas as pd

from harness.descriptors import keys as descriptor_keys
from harness.descriptors.base import make_descriptor
from harness.descriptors.config import DescriptorConfig, ProjectionConfig
from harness.descriptors.extract import (
    combine_shards,
    encode_shard,
    fit_projection_unit,
    train_model,
)
from harness.runtime.stage import Build, Entry, Table, Units


def descriptor_model(
    p: Units, dc: DescriptorConfig, frames: Table, props: dict[str, Table]
) -> Entry:
    """Proposals -> the trained model of descriptor ``dc`` (empty for one that does not train).

    ``props``: the proposals of the sessions it trains on.
    """
    trains = make_descriptor(dc).needs_training
    rows = (
        pd.concat([t.df for t in props.values()], ignore_index=True) if trains else pd.DataFrame()
    )
    build = partial(train_model, dc, frames.df, rows)
    key = descriptor_keys.model(dc, trains, [t.key for t in props.values()])
    return p.unit("model", key, build)


def descriptor_projection(
    p: Units,
    dc: DescriptorConfig,
    pc: ProjectionConfig,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
    model: Entry,
) -> Entry | None:
    """Model -> the compact-descriptor projection (``[projection] dim > 0``).

    Fitted on the reference sessions: those some pair ranks against. None when the projection
    is off.
    """
    if pc.dim == 0:
        return None
    refs = sorted(set(pairs.df["r_session"]))
    rows = pd.concat([props[s].df for s in refs], ignore_index=True)
    build = partial(fit_projection_unit, dc, pc, model.path, frames.df, rows)
    key = descriptor_keys.projection(pc, dc, model.key, [props[s].key for s in refs])
    return p.unit("projection", key, build)


def session_descriptors(
    p: Units,
    dc: DescriptorConfig,
    frames: Table,
    props: dict[str, Table],
    model: Entry,
    projection: Entry | None = None,
) -> dict[str, Entry]:
    """Proposals + model (+ projection) -> each session's descriptors.

    ``desc.npy``, aligned with ``index.parquet``.

    Work is cached in shards of ``shard_frames`` frames (an interrupted extraction resumes at the
    next unfinished shard); a session's shards are then combined, one shard at a time.
    """
    fkey = projection.key if projection else None

    def shard(s: str, rows: pd.DataFrame, ut: list[int], label: str) -> tuple[Any, Build]:
        fr = frames.df[frames.df["session"] == s]
        path = projection.path if projection else None
        build = partial(encode_shard, dc, model.path, path, fr, rows, label)
        return descriptor_keys.descriptor_shard(dc, props[s].key, model.key, ut, fkey), build

    def combine(s: str, parts: list[Entry]) -> tuple[Any, Build]:
        build = partial(combine_shards, dc, props[s].df, [e.path for e in parts])
        key = descriptor_keys.descriptors(dc, props[s].key, model.key, [e.key for e in parts])
        return key, build

    stages = ("descriptor_shards", "descriptors")
    return p.sharded(stages, props, dc.shard_frames, shard, combine, gpu=True)[0]

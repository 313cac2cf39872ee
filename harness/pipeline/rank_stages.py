"""The ranking stages (SPEC 6 and 12): each query subimage's rank of its true place.

Computed by the run's descriptor and engine, or imported from a user's ranked lists.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from harness.errors import RetrievalError
from harness.pipeline.context import Context
from harness.records import SUBIMAGE_KEY
from harness.retrieval import keys as retrieval_keys
from harness.retrieval.config import RetrievalConfig
from harness.retrieval.import_file import ImportSpec
from harness.retrieval.imported import unranked_images, write_imported_ranks
from harness.retrieval.units import RankSettings, rank_reference
from harness.runtime.cache import (
    read_cached_parquet,
    write_parquet,
)
from harness.runtime.hardware import rank_precision
from harness.runtime.stage import Build, Entry, RankTable, Table


def ranks_device(rc: RetrievalConfig, dev: str) -> str:
    """The exact engine's device: CUDA when ``dev`` (the descriptor's) allows it and one exists."""
    import torch

    return (
        "cuda"
        if rc.engine == "exact" and dev in ("auto", "cuda") and torch.cuda.is_available()
        else "cpu"
    )


def query_ranks(
    p: Context,
    frames: Table,
    pairs: Table,
    described: dict[str, Entry],
    rc: RetrievalConfig,
    device: str = "auto",
    precision: str = "fp32",
) -> RankTable:
    """Pairs + descriptors -> the rank of each query subimage's ground-truth place (SPEC section 6).

    Units: (reference session, chunk of ``query_frames_per_shard`` pairs); one engine per
    proposal method inside each. ``rc``: the ``[retrieval]`` to rank under (the run's, or
    ``gt_radius_also``'s). ``device``: the descriptor's (``[descriptor] device``); the exact
    engine runs on CUDA where it allows and one is present. ``precision``: the descriptor's
    (``[descriptor] precision``), for the exact engine's candidate product
    (:func:`harness.runtime.hardware.rank_precision`).
    """
    dkeys = {s: e.key for s, e in described.items()}
    paths, device = {s: e.path for s, e in described.items()}, ranks_device(rc, device)
    precision = rank_precision(precision) if rc.engine == "exact" else "fp32"
    units: list[tuple[tuple[Any, ...], Build]] = []
    unit_ref = []
    step = max(1, rc.query_frames_per_shard)
    for ref in [s.name for s in p.cfg.sessions]:
        sub = pairs.df[pairs.df["r_session"] == ref].reset_index(drop=True)
        for c0 in range(0, max(len(sub), 1), step):
            chunk = sub.iloc[c0 : c0 + step]
            settings = RankSettings(
                rc,
                p.cfg.pairs.max_yaw_diff_deg,
                device,
                p.cfg.pairs.place_frames if p.cfg.pairs.by != "pose" else None,
                precision,
            )
            build = partial(_write_ranks, settings, chunk, ref, paths, frames.df)
            key = retrieval_keys.ranks_unit(rc, ref, pairs.key, dkeys, c0, len(chunk), precision)
            units.append((key, build))
            unit_ref.append(ref)
    parts: list[pd.DataFrame] = []
    counts: dict[str, dict[str, int]] = {}
    for ref, entry in zip(unit_ref, p.units("ranks", units, gpu=True), strict=True):
        parts.append(read_cached_parquet(entry.path / "ranks.parquet"))
        c = counts.setdefault(ref, {})
        for k, v in p.cache.manifest("ranks", entry.key)["info"].items():
            c[k] = c.get(k, 0) + v
    df = concat_ranks(parts)
    return RankTable(df, retrieval_keys.rank_table(rc, pairs.key, dkeys, precision), counts)


SORT_RANKS = SUBIMAGE_KEY


def concat_ranks(parts: list[pd.DataFrame]) -> pd.DataFrame:
    """Units' rank rows as one table in subimage order (empty units left out)."""
    parts = [d for d in parts if len(d)]
    if not parts:
        return pd.DataFrame()
    return pd.concat(parts, ignore_index=True).sort_values(SORT_RANKS).reset_index(drop=True)


def _write_ranks(
    settings: RankSettings,
    pairs: pd.DataFrame,
    ref: str,
    descriptors: dict[str, Path],
    frames: pd.DataFrame,
    tmp: Path,
) -> dict[str, int]:
    """One ranking unit (:func:`harness.retrieval.rank_reference`) into ``tmp/ranks.parquet``."""
    df, counts = rank_reference(settings, pairs, ref, descriptors, frames)
    write_parquet(tmp / "ranks.parquet", df)
    return counts


def imported_ranks(
    p: Context,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
    spec: ImportSpec,
    score_kind: str,
    rc: RetrievalConfig,
) -> RankTable:
    """Ranks from a user's localizer (``--import NAME=FILE`` or an ``import`` localizer).

    Checked against the run (SPEC 12): every row must be a proposal of the run and match a pair;
    a query image of the pairs without any row is an error unless ``[import]
    allow_unranked_images`` (then it is counted).
    """
    if not Path(spec.path).is_file():
        raise RetrievalError(f"{spec.path}: --import file not found (localizer {spec.name!r})")
    allprops = pd.concat([t.df for t in props.values()], ignore_index=True)
    build = partial(
        write_imported_ranks,
        spec,
        pairs.df,
        frames.df,
        allprops,
        rc.gt_radius_m,
        p.cfg.pairs.max_yaw_diff_deg,
        score_kind,
    )
    key = retrieval_keys.ranks_import(
        rc,
        p.cfg.import_,
        p.cfg.pairs.max_yaw_diff_deg,
        spec.name,
        spec.path,
        pairs.key,
        [t.key for t in props.values()],
        score_kind,
    )
    entry = p.unit("ranks", key, build)
    df = read_cached_parquet(entry.path / "ranks.parquet")
    info = dict(p.cache.manifest("ranks", entry.key)["info"])
    missing = unranked_images(pairs.df, df)
    info["unranked_query_images"] = len(missing)
    if len(missing) and not p.cfg.import_.allow_unranked_images:
        ex = missing.iloc[0]
        raise RetrievalError(
            f"{spec.path}: localizer {spec.name!r} ranks no subimage of {len(missing)} of "
            f"{len(pairs.df)} query images (e.g. {ex.q_session}/{ex.q_camera}/{ex.q_utime} -> "
            f"{ex.r_session}); every localizer is scored on the same images: rank them, or set "
            "[import] allow_unranked_images = true to leave them out of every table (counted)"
        )
    return RankTable(df, entry.key, {"import": info})

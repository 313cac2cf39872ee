"""The ranking stages (method §6, 12): ranks by descriptors or words, or from a user's file.

Their keys are made in :mod:`harness.retrieval.keys`; a ranking unit is
:func:`harness.retrieval.units.rank_reference`.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from harness.errors import RetrievalError
from harness.records import SUBIMAGE_KEY
from harness.retrieval import keys as retrieval_keys
from harness.retrieval.bovw import combine_word_shards, encode_words, train_vocabulary
from harness.retrieval.config import BovwConfig, ImportConfig, RetrievalConfig
from harness.retrieval.import_file import ImportSpec
from harness.retrieval.imported import unranked_images, write_imported_ranks
from harness.retrieval.units import RankSettings, rank_reference
from harness.runtime.cache import read_cached_parquet, write_parquet
from harness.runtime.stage import Build, Entry, RankTable, Table, Units


def rank_queries(
    p: Units,
    how: RankSettings,
    refs: Sequence[str],
    frames: Table,
    pairs: Table,
    described: dict[str, Entry],
) -> RankTable:
    """Pairs + descriptors -> the rank of each query subimage's ground-truth place (method §6).

    Units: (reference session of ``refs``, chunk of ``query_frames_per_shard`` pairs); one engine
    per proposer inside each. ``how``: the ``[retrieval]`` to rank under, the heading limit, and
    the engine's device and candidate product as they resolve here.
    """
    rc = how.rc
    dkeys = {s: e.key for s, e in described.items()}
    paths = {s: e.path for s, e in described.items()}
    units: list[tuple[tuple[Any, ...], Build]] = []
    unit_ref = []
    step = max(1, rc.query_frames_per_shard)
    for ref in refs:
        sub = pairs.df[pairs.df["r_session"] == ref].reset_index(drop=True)
        for c0 in range(0, max(len(sub), 1), step):
            chunk = sub.iloc[c0 : c0 + step]
            build = partial(_write_ranks, how, chunk, ref, paths, frames.df)
            key = retrieval_keys.ranks_unit(
                rc, ref, pairs.key, dkeys, c0, len(chunk), how.precision
            )
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
    return RankTable(df, retrieval_keys.rank_table(rc, pairs.key, dkeys, how.precision), counts)


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
    p: Units,
    rc: RetrievalConfig,
    imp: ImportConfig,
    max_yaw_diff_deg: float,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
    spec: ImportSpec,
) -> RankTable:
    """Ranks from a user's localizer (``--import NAME=FILE`` or an ``import`` localizer).

    Checked against the run (method §12): every row must be a proposal of the run and match a pair;
    a query image of the pairs without any row is an error unless ``[import]
    allow_unranked_images`` (then it is counted). ``imp``: ``[import]`` with the localizer's
    ``score_kind``.
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
        max_yaw_diff_deg,
        imp.score_kind,
    )
    key = retrieval_keys.ranks_import(
        rc,
        imp,
        max_yaw_diff_deg,
        spec.name,
        spec.path,
        pairs.key,
        [t.key for t in props.values()],
        imp.score_kind,
    )
    entry = p.unit("ranks", key, build)
    df = read_cached_parquet(entry.path / "ranks.parquet")
    info = dict(p.cache.manifest("ranks", entry.key)["info"])
    missing = unranked_images(pairs.df, df)
    info["unranked_query_images"] = len(missing)
    if len(missing) and not imp.allow_unranked_images:
        ex = missing.iloc[0]
        raise RetrievalError(
            f"{spec.path}: localizer {spec.name!r} ranks no subimage of {len(missing)} of "
            f"{len(pairs.df)} query images (e.g. {ex.q_session}/{ex.q_camera}/{ex.q_utime} -> "
            f"{ex.r_session}); every localizer is scored on the same images: rank them, or set "
            "[import] allow_unranked_images = true to leave them out of every table (counted)"
        )
    return RankTable(df, entry.key, {"import": info})


def bovw_vocabulary(
    p: Units, bc: BovwConfig, frames: Table, pairs: Table, props: dict[str, Table]
) -> Entry:
    """Reference-session subimages -> a bag-of-words vocabulary and its IDF (method §11)."""
    refs = sorted(set(pairs.df["r_session"]))
    rows = pd.concat([props[s].df for s in refs], ignore_index=True)
    build = partial(train_vocabulary, bc, frames.df, rows)
    return p.unit("bovw_vocab", retrieval_keys.bovw_vocab(bc, [props[s].key for s in refs]), build)


def bovw_words(
    p: Units, bc: BovwConfig, name: str, frames: Table, props: dict[str, Table], vocab: Entry
) -> tuple[dict[str, Entry], int]:
    """Each session's word vectors (``words.npz`` + ``index.parquet``), in resumable shards.

    ``name``: the localizer's, in the progress labels.

    Returns:
        The entries, and how many subimages had no feature (no vector, counted).
    """

    def shard(s: str, rows: pd.DataFrame, ut: list[int], label: str) -> tuple[Any, Build]:
        fr = frames.df[frames.df["session"] == s]
        mine = rows.reset_index(drop=True)
        build = partial(encode_words, bc, vocab.path, fr, mine, f"{name} {label}")
        return retrieval_keys.bovw_shard(vocab.key, props[s].key, ut), build

    def combine(s: str, parts: list[Entry]) -> tuple[Any, Build]:
        build = partial(combine_word_shards, [e.path for e in parts])
        return retrieval_keys.bovw_words(vocab.key, props[s].key, [e.key for e in parts]), build

    out, done = p.sharded(("bovw_shards", "bovw_words"), props, bc.shard_frames, shard, combine)
    nofeat = sum(
        int(p.cache.manifest("bovw_shards", e.key)["info"].get("no_feature_subimages", 0))
        for e in done
    )
    return out, nofeat

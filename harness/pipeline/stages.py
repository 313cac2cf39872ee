"""The pipeline's stages (SPEC sections 3-10), in data-flow order.

Each is a function of the :class:`~harness.pipeline.context.Context` and the typed outputs of the
stages before it.
Each builds its cache key with :mod:`harness.pipeline.keys` and hands a build function (a
module-level function of the stage's module, bound with :func:`functools.partial`) to the cache.
"""

from __future__ import annotations

import logging
import time
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from harness.config.schema import Config
from harness.descriptors import keys as descriptor_keys
from harness.descriptors import make_descriptor
from harness.descriptors.config import DescriptorConfig
from harness.descriptors.extract import (
    combine_shards,
    encode_shard,
    fit_projection_unit,
    train_model,
)
from harness.errors import AnnotationError, ConfigError
from harness.fusion import keys as fusion_keys
from harness.fusion.config import FusionConfig
from harness.fusion.samples import write_samples
from harness.imagestore import local_uri
from harness.ingest import combine_frames, ingest_session
from harness.ingest import keys as ingest_keys
from harness.ingest.annotations import COLUMNS, load_annotations
from harness.ingest.annotations import validate as validate_annotations
from harness.ingest.masks import read_masks
from harness.ingest.names import frames_by_image, session_names
from harness.pairs import keys as pair_keys
from harness.pairs.build import DECLARED, candidate_pairs, write_pairs
from harness.pipeline.context import Context
from harness.proposals import keys as proposal_keys
from harness.proposals.proposers import write_proposals
from harness.records import FRAME_KEY
from harness.reports.blocks import Block, Reports
from harness.reports.write import write_reports
from harness.retrieval import described_frames
from harness.retrieval.pairing import write_retrieval_pairs
from harness.runtime.cache import (
    read_cached_parquet,
)
from harness.runtime.progress import progress
from harness.runtime.stage import Build, Entry, RankTable, Table

log = logging.getLogger(__name__)

# ---------------------------------------------------------------- the stages, in data-flow order


def ingest_logs(p: Context) -> dict[str, Entry]:
    """Logs -> one ingest entry per session (``frames.parquet``, images, ``ingest_report.json``)."""
    units: list[tuple[tuple[Any, ...], Build]] = [
        (
            ingest_keys.ingest(p.cfg.ingest, sc, p.cfg.data_root),
            partial(ingest_session, sc, p.cfg.ingest),
        )
        for sc in p.cfg.sessions
    ]
    return dict(zip([sc.name for sc in p.cfg.sessions], p.units("ingest", units), strict=True))


def frame_table(p: Context, ingested: dict[str, Entry]) -> Table:
    """Ingest entries -> the run's frame table (image URIs local to this machine)."""
    build = partial(
        combine_frames,
        [e.path for e in ingested.values()],
        p.out,
        p.cfg.data_root,
        sources=[sc.source for sc in p.cfg.sessions],
    )
    entry = p.unit("frames", ingest_keys.frames([e.key for e in ingested.values()]), build)
    df = read_cached_parquet(entry.path / "frames.parquet")
    df["image"] = [local_uri(u, p.out, p.cfg.data_root) for u in df["image"]]
    return Table(df, entry.key)


def annotation_table(p: Context, frames: Table) -> Table:
    """The annotations (file, mask folder or both), checked against the frames.

    Rows that name their image (``image``: a folder session's file, SPEC 13.2) and masks
    (``[masks] folder``) get their frame keys from the folder sessions' file names; a frame
    annotated in both is an error. The key is the contents' hash.
    """
    parts, digests = [], []
    names = session_names(p.cfg.sessions)
    skip = getattr(p, "train_sessions", None) or ()
    path = p.cfg.annotations
    if path is not None:
        if p.annotations_optional:  # harness detect: the rows of the sessions it reads
            every = load_annotations(path, None, names, skip)
            every = every[every["session"].isin({s.name for s in p.cfg.sessions})]
            every = validate_annotations(every.reset_index(drop=True), frames.df, str(path))
        else:
            every = load_annotations(path, frames.df, names, skip)
        parts.append(every)
        digests.append(ingest_keys.annotation_file(path))
    mk = p.cfg.masks
    if mk.folder is not None:
        rows, counts = read_masks(Path(mk.folder), mk.min_mask_area)
        at = [f"mask {n}" for n in rows["image"]]
        parts.append(frames_by_image(rows, names, frames.df, skip, mk.folder, at))
        digests.append(ingest_keys.masks(Path(mk.folder), mk.min_mask_area))
        log.info("masks: %s: %s", mk.folder, counts)
    if not parts:  # harness detect without annotations: no frame is annotated
        return Table(validate_annotations(pd.DataFrame(columns=COLUMNS), None, "none"), "none")
    if len(parts) == 1 and path is not None:
        return Table(parts[0], digests[0])
    both = pd.concat([x[COLUMNS] for x in parts], ignore_index=True)
    if len(parts) == 2:
        twice = set(map(tuple, parts[0][FRAME_KEY].to_numpy())) & set(
            map(tuple, parts[1][FRAME_KEY].to_numpy())
        )
        if twice:
            s, c, u = sorted(twice)[0]
            raise AnnotationError(
                f"{mk.folder}: frame {s} {c} {u} is annotated both in {path} and by a mask"
            )
    where = str(mk.folder) if path is None else f"{path} + {mk.folder}"
    return Table(
        validate_annotations(both, frames.df, where), ingest_keys.annotation_sources(digests)
    )


def query_pairs(p: Context, frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> a reference viewpoint per query frame and season (SPEC 4)."""
    queries = ann.df if p.cfg.pairs.queries == "annotated" else None
    build = partial(_write_pairs, frames.df, p.cfg, queries)
    entry = p.unit(
        "pairs", pair_keys.pairs(p.cfg.pairs, p.cfg.seasons(), frames.key, ann.key), build
    )
    return Table(read_cached_parquet(entry.path / "pairs.parquet"), entry.key)


def _write_pairs(
    frames: pd.DataFrame, cfg: Config, queries: pd.DataFrame | None, tmp: Path
) -> dict:
    """The pairs stage's build.

    The folder sessions' file names are read only where pairs need them (``[pairs] by =
    "name"`` or ``"order"``).
    """
    names = session_names(cfg.sessions) if cfg.pairs.by in DECLARED else None
    if cfg.pairs.by == "name" and names is not None and not len(names):
        raise ConfigError(
            "[pairs] by = 'name' pairs images by their file names, and no session is a folder "
            "of images (logs have no file names): use by = 'order', 'sequence' or 'retrieval'"
        )
    return write_pairs(frames, cfg.pairs, cfg.seasons(), queries, names, tmp)


def candidate_table(p: Context, frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> query frames and the sessions to pair them with (SPEC 13.2).

    ``[pairs] by = "retrieval"``: the frame each is paired with comes later, from the
    localizer's descriptors (:func:`retrieval_pair_table`).
    """
    queries = ann.df if p.cfg.pairs.queries == "annotated" else None
    cand = candidate_pairs(frames.df, p.cfg.seasons(), queries)
    return Table(cand, pair_keys.candidates(p.cfg.pairs, p.cfg.seasons(), frames.key, ann.key))


def retrieval_pair_table(
    p: Context, frames: Table, cand: Table, described: dict[str, Entry], proposer: str
) -> Table:
    """Candidates + descriptors -> each query frame's map frame by retrieval (SPEC 13.2)."""
    paths = {s: e.path for s, e in described.items()}
    build = partial(
        write_retrieval_pairs,
        cand.df,
        paths,
        frames.df,
        proposer,
        p.cfg.retrieval.memory_mb,
        p.cfg.pairs.place_frames,
        p.cfg.pairs.sequence_frames if p.cfg.pairs.by == "sequence" else 0,
    )
    dkeys = {s: e.key for s, e in described.items()}
    entry = p.unit("pairs_retrieval", pair_keys.by_retrieval(cand.key, dkeys, proposer), build)
    return Table(read_cached_parquet(entry.path / "pairs.parquet"), entry.key)


def session_proposals(
    p: Context, frames: Table, pairs: Table, ingested: dict[str, Entry]
) -> dict[str, Table]:
    """Frames + pairs -> each session's proposal boxes (SPEC section 5).

    Only on the frames ranking reads.

    Those are a session's query frames and, for a reference session, the frames its database keeps
    (every frame unless ``[retrieval] db_stride_m``); the others are counted in ``run.json``
    (``counts.frames_not_described``), never proposed or encoded.
    """
    out = {}
    described = described_frames(frames.df, pairs.df, p.cfg.retrieval.db_stride_m)
    empty = frames.df.iloc[:0]
    for sc in p.cfg.sessions:
        fr = described.get(sc.name, empty)
        p.not_described[sc.name] = int((frames.df["session"] == sc.name).sum()) - len(fr)
        build = partial(write_proposals, fr, p.cfg.proposals, sc.name)
        used = [(str(c), int(u)) for c, u in zip(fr["camera"], fr["utime"], strict=True)]
        entry = p.unit(
            "proposals",
            proposal_keys.proposals(p.cfg.proposals, ingested[sc.name].key, used),
            build,
        )
        out[sc.name] = Table(read_cached_parquet(entry.path / "proposals.parquet"), entry.key)
    return out


def descriptor_model(
    p: Context, dc: DescriptorConfig, frames: Table, props: dict[str, Table]
) -> Entry:
    """Proposals -> the trained model of descriptor ``dc`` (empty for one that does not train)."""
    trains = make_descriptor(dc).needs_training
    if p.train_sessions is not None:
        props = {s: t for s, t in props.items() if s in p.train_sessions}
    rows = (
        pd.concat([t.df for t in props.values()], ignore_index=True) if trains else pd.DataFrame()
    )
    build = partial(train_model, dc, frames.df, rows)
    return p.unit(
        "model", descriptor_keys.model(dc, trains, [t.key for t in props.values()]), build
    )


def descriptor_projection(
    p: Context,
    dc: DescriptorConfig,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
    model: Entry,
) -> Entry | None:
    """Model -> the compact-descriptor projection (``[projection] dim > 0``).

    Fitted on the reference sessions.

    The reference sessions are those some pair ranks against; None when the projection is off.
    """
    if p.cfg.projection.dim == 0:
        return None
    refs = sorted(set(pairs.df["r_session"]))
    rows = pd.concat([props[s].df for s in refs], ignore_index=True)
    build = partial(fit_projection_unit, dc, p.cfg.projection, model.path, frames.df, rows)
    return p.unit(
        "projection",
        descriptor_keys.projection(p.cfg.projection, dc, model.key, [props[s].key for s in refs]),
        build,
    )


def session_descriptors(
    p: Context,
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
        return descriptor_keys.descriptors(
            dc, props[s].key, model.key, [e.key for e in parts]
        ), build

    stages = ("descriptor_shards", "descriptors")
    return p.sharded(stages, props, dc.shard_frames, shard, combine, gpu=True)[0]


def fused_samples(
    p: Context, ranks: RankTable, frames: Table, ann: Table, fusion: FusionConfig | None = None
) -> Table:
    """Ranks + annotations -> a sample per fused box with each method's LoC (SPEC 7-8)."""
    fc = fusion or p.cfg.fusion
    build = partial(write_samples, ranks.df, frames.df, ann.df, fc)
    entry = p.unit("samples", fusion_keys.samples(fc, p.cfg.splits, ranks.key, ann.key), build)
    return Table(read_cached_parquet(entry.path / "samples.parquet"), entry.key)


def change_tables(p: Context, blocks: list[Block], frames: Table, ann: Table) -> Reports:
    """Samples -> Tables I, S, P (and L), localization quality, splits and figures (SPEC 8-11).

    One block per localizer (and ``all localizers`` where there are several); a block's notes
    are printed under its change tables (what the localizer lacks or lost).
    """
    t0 = time.perf_counter()
    reports = write_reports(
        p.cfg,
        p.out,
        blocks,
        frames=frames.df,
        ann=ann.df,
        progress=partial(progress, desc="splits", unit="split"),
    )
    p.timings["labels_ap_reports"] = time.perf_counter() - t0
    return reports

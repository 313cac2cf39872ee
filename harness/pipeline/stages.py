"""The pipeline's stages (SPEC sections 3-10), in data-flow order.

Each is a function of the :class:`~harness.pipeline.context.Context` and the typed outputs of the
stages before it.
Each builds its cache key with :mod:`harness.pipeline.keys` and hands a build function (a
module-level function of the stage's module, bound with :func:`functools.partial`) to the cache.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from harness.config.schema import Config
from harness.descriptors import REGISTRY, make_descriptor
from harness.descriptors.config import DescriptorConfig
from harness.descriptors.extract import (
    combine_shards,
    encode_shard,
    fit_projection_unit,
    train_model,
)
from harness.errors import AnnotationError, ConfigError, IngestError, RetrievalError
from harness.fixture import FixtureSpec, generate
from harness.fixture.generate import read_spec
from harness.fusion.config import FusionConfig
from harness.fusion.fuse import write_samples
from harness.imagestore import local_uri
from harness.ingest import combine_frames, ingest_session
from harness.ingest.annotations import COLUMNS, load_annotations
from harness.ingest.annotations import validate as validate_annotations
from harness.ingest.logs import detect_format, known_formats
from harness.ingest.masks import folder_digest, read_masks
from harness.ingest.names import frames_by_image, session_names
from harness.inputs import check_input
from harness.pairs.build import DECLARED, candidate_pairs, write_pairs
from harness.pipeline import keys
from harness.pipeline.context import Build, Context, Entry, RankTable, Table
from harness.proposals.proposers import write_proposals
from harness.records import FRAME_KEY, SUBIMAGE_KEY
from harness.reports.write import Block, Reports, write_reports
from harness.retrieval import described_frames, rank_reference
from harness.retrieval.config import RetrievalConfig
from harness.retrieval.import_file import ImportSpec
from harness.retrieval.imported import unranked_images, write_imported_ranks
from harness.retrieval.pairing import write_retrieval_pairs
from harness.runtime.cache import (
    content_sha,
    read_cached_parquet,
    stable_hash,
    write_parquet,
    write_text,
)
from harness.runtime.hardware import rank_precision
from harness.runtime.progress import progress

log = logging.getLogger(__name__)

# ---------------------------------------------------------------- the stages, in data-flow order


def generate_fixture(p: Context) -> None:
    """Generate the fixture into ``data_root`` when ``[fixture] generate`` and it is absent.

    An existing fixture is reused as it is. A ``data_root`` that exists and holds anything else
    is never touched: that is someone's data, and the error says so.
    """
    fx, root = p.cfg.fixture, p.cfg.data_root
    if not fx.generate:
        return
    if (root / "fixture.json").exists():
        check_fixture_spec(p)
        return
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise ConfigError(
            f"{root}: [fixture] generate = true, but data_root exists and holds no "
            "generated fixture "
            "(no fixture.json); the harness never writes into it. Set generate = false for "
            "real data, "
            "or point data_root (--data-root) at a new directory"
        )

    log.info("fixture: generating into %s", root)
    spec = FixtureSpec.chosen(fx)
    t0 = time.perf_counter()
    try:
        generate(root, spec, formats=fx.formats or None)
    except ValueError as err:
        raise ConfigError(f"[fixture] {err}") from None
    p.timings["fixture"] = time.perf_counter() - t0
    if p.cfg.annotations is not None and not p.cfg.annotations.exists():
        p.cfg.annotations.parent.mkdir(parents=True, exist_ok=True)
        write_text(p.cfg.annotations, (root / "annotations.csv").read_text())


def check_fixture_spec(p: Context) -> None:
    """An existing generated fixture must be the one ``[fixture]`` describes.

    Raises:
        ConfigError: it was generated with other settings (naming them); it is never replaced
            silently: the message says to remove it so that the next run generates it again.
    """
    fx, root = p.cfg.fixture, p.cfg.data_root
    try:
        have = read_spec(root)
    except (OSError, ValueError, KeyError):
        return  # an unreadable record: ingest reports what is wrong with the data
    want = {
        "seed": fx.seed,
        "frames": fx.frames,
        "width": fx.width,
        "height": fx.height,
        "objects": fx.objects,
        "loop_scale": fx.loop_scale,
        "render_scale": fx.render_scale,
    }
    diff = {k: (have.get(k), v) for k, v in want.items() if k in have and have.get(k) != v}
    if diff:
        raise ConfigError(
            f"{root}: a fixture generated with other [fixture] settings ("
            + ", ".join(f"{k} {a!r} there, {b!r} in the config" for k, (a, b) in diff.items())
            + f"); remove {root} (the harness generated it) and run again to regenerate it"
        )


def check_names(p: Context) -> None:
    """Registry names of the config, checked before the fixture is generated or anything read.

    A descriptor registered at run time counts.

    Raises:
        ConfigError: An unknown descriptor or log format, naming the known ones.
    """
    cfg = p.cfg
    for loc in p.localizer_list:
        if loc.descriptor is not None and loc.descriptor.name not in REGISTRY:
            where = "[descriptor]" if not cfg.localizers else f"localizer {loc.name}: descriptor"
            raise ConfigError(
                f"{where} name = {loc.descriptor.name!r}: unknown; known: {sorted(REGISTRY)}"
            )
    for sc in cfg.sessions:
        if sc.format != "auto" and sc.format not in known_formats():
            raise ConfigError(
                f"sessions {sc.name}: format = {sc.format!r}: unknown; known: "
                f"{list(known_formats())}"
            )


def preflight(p: Context) -> None:
    """Every input the config names checked before any stage runs (nothing half done).

    Every session's log (present, readable, of a known format, an NCLT session's camera), the
    annotation file and a proposal table.

    Raises:
        HarnessError: Naming the key or the file and what is wrong.
    """
    cfg = p.cfg
    for sc in cfg.sessions:
        src = Path(sc.source)
        check_input(src, f"log of session {sc.name}", IngestError, directory=src.is_dir())
        fmt = detect_format(src) if sc.format == "auto" else sc.format
        cams = src / "images" / sc.name / "lb3"
        if fmt == "nclt" and not (cams / sc.camera).is_dir():
            found = sorted(d.name for d in cams.glob("*") if d.is_dir()) if cams.is_dir() else []
            raise ConfigError(
                f"sessions {sc.name}: camera = {sc.camera!r}: no {cams / sc.camera}; cameras "
                f"found: {found or 'none'} (names are case-sensitive)"
            )
    if cfg.annotations is None:
        if not p.annotations_optional:
            raise ConfigError(
                "missing required key 'annotations': the tables measure change against an "
                "annotation file (harness detect runs without one)"
            )
    else:
        check_input(cfg.annotations, "annotation file", AnnotationError)
    if "file" in cfg.proposals.methods and cfg.proposals.file:
        check_input(cfg.proposals.file, "[proposals] file", ConfigError)


def ingest_logs(p: Context) -> dict[str, Entry]:
    """Logs -> one ingest entry per session (``frames.parquet``, images, ``ingest_report.json``)."""
    units: list[tuple[tuple[Any, ...], Build]] = [
        (keys.ingest(p.cfg, sc), partial(ingest_session, sc, p.cfg.ingest)) for sc in p.cfg.sessions
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
    entry = p.unit("frames", keys.frames([e.key for e in ingested.values()]), build)
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
        digests.append(content_sha(path))
    mk = p.cfg.masks
    if mk.folder is not None:
        rows, counts = read_masks(Path(mk.folder), mk.min_mask_area)
        at = [f"mask {n}" for n in rows["image"]]
        parts.append(frames_by_image(rows, names, frames.df, skip, mk.folder, at))
        digests.append(stable_hash("masks", folder_digest(Path(mk.folder)), mk.min_mask_area))
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
    key = digests[0] if len(digests) == 1 else stable_hash(*digests)
    return Table(validate_annotations(both, frames.df, where), key)


def query_pairs(p: Context, frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> a reference viewpoint per query frame and season (SPEC 4)."""
    queries = ann.df if p.cfg.pairs.queries == "annotated" else None
    build = partial(_write_pairs, frames.df, p.cfg, queries)
    entry = p.unit("pairs", keys.pairs(p.cfg, frames.key, ann.key), build)
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
    return Table(cand, stable_hash("candidates", *keys.pairs(p.cfg, frames.key, ann.key)))


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
    entry = p.unit("pairs_retrieval", (cand.key, dkeys, proposer), build)
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
        entry = p.unit("proposals", keys.proposals(p.cfg, ingested[sc.name].key, used), build)
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
    return p.unit("model", keys.model(dc, trains, [t.key for t in props.values()]), build)


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
        keys.projection(p.cfg.projection, dc, model.key, [props[s].key for s in refs]),
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
        return keys.descriptor_shard(dc, props[s].key, model.key, ut, fkey), build

    def combine(s: str, parts: list[Entry]) -> tuple[Any, Build]:
        build = partial(combine_shards, dc, props[s].df, [e.path for e in parts])
        return keys.descriptors(dc, props[s].key, model.key, [e.key for e in parts]), build

    stages = ("descriptor_shards", "descriptors")
    return p.sharded(stages, props, dc.shard_frames, shard, combine, gpu=True)[0]


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
            build = partial(
                _write_ranks,
                rc,
                p.cfg.pairs.max_yaw_diff_deg,
                chunk,
                ref,
                paths,
                frames.df,
                device,
                p.cfg.pairs.place_frames if p.cfg.pairs.by != "pose" else None,
                precision,
            )
            key = keys.ranks_unit(rc, ref, pairs.key, dkeys, c0, len(chunk), precision)
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
    return RankTable(df, stable_hash(*keys.ranks(rc, pairs.key, dkeys, precision)), counts)


SORT_RANKS = SUBIMAGE_KEY


def concat_ranks(parts: list[pd.DataFrame]) -> pd.DataFrame:
    """Units' rank rows as one table in subimage order (empty units left out)."""
    parts = [d for d in parts if len(d)]
    if not parts:
        return pd.DataFrame()
    return pd.concat(parts, ignore_index=True).sort_values(SORT_RANKS).reset_index(drop=True)


def _write_ranks(
    rc: Any,
    max_yaw_deg: float,
    pairs: pd.DataFrame,
    ref: str,
    descriptors: dict[str, Path],
    frames: pd.DataFrame,
    device: str,
    place_frames: int | None,
    precision: str,
    tmp: Path,
) -> dict[str, int]:
    """One ranking unit (:func:`harness.retrieval.rank_reference`) into ``tmp/ranks.parquet``."""
    df, counts = rank_reference(
        rc, max_yaw_deg, pairs, ref, descriptors, frames, device, place_frames, precision
    )
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
    key = keys.ranks_import(
        p.cfg,
        rc,
        spec.name,
        content_sha(spec.path),
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


def fused_samples(
    p: Context, ranks: RankTable, frames: Table, ann: Table, fusion: FusionConfig | None = None
) -> Table:
    """Ranks + annotations -> a sample per fused box with each method's LoC (SPEC 7-8)."""
    fc = fusion or p.cfg.fusion
    cfg = p.cfg if fusion is None else dataclasses.replace(p.cfg, fusion=fc)
    build = partial(write_samples, ranks.df, frames.df, ann.df, fc)
    entry = p.unit("samples", keys.samples(cfg, ranks.key, ann.key), build)
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

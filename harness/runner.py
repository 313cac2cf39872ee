"""The pipeline (SPEC sections 3-10) as a chain of stage calls.

logs -> frames -> pairs -> proposals -> model [-> projection] -> descriptors -> ranks -> samples ->
tables

Each stage is a module-level function of typed inputs (the :class:`Pipeline` context and the
outputs of the stages before it) to a typed output. It builds its cache key with
:mod:`harness.keys` and hands a build function (a module-level function of the stage's module,
bound with :func:`functools.partial`) to the cache: an entry ``<out>/cache/<stage>/<key>/`` is
built once, so a rerun with nothing changed does no work, an interrupted run resumes, and
changing one option reruns only what depends on it. ``docs/architecture.md`` draws the chain.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import platform
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from . import __version__, keys
from .annotations import COLUMNS, load_annotations
from .annotations import validate as validate_annotations
from .cache import (
    StageCache,
    content_sha,
    read_cached_parquet,
    stable_hash,
    write_json,
    write_parquet,
    write_text,
)
from .config import (
    ALL_LOCALIZERS,
    Config,
    FusionConfig,
    LocalizerConfig,
    LocalizerImportConfig,
)
from .descriptors import make_descriptor
from .descriptors.extract import combine_shards, encode_shard, fit_projection_unit, train_model
from .errors import AnnotationError, ConfigError, HarnessError, IngestError, RetrievalError
from .executors import LocalExecutor
from .fusion import write_samples
from .imagestore import local_uri
from .ingest import combine_frames, ingest_session
from .methods import ordered_methods
from .outdirs import claim_dir, read_run_record, run_lock
from .pairs import write_pairs
from .progress import progress
from .proposals import write_proposals
from .reports import Block, Reports, write_reports
from .retrieval import described_frames, rank_reference
from .retrieval.imported import ImportSpec, parse_import_arg, unranked_images

#: Fusion methods that need the relevance score d (SPEC section 7).
SCORE_ONLY = ("score_max", "score_sum")
#: Methods not defined across localizers (SPEC section 11).
NOT_ACROSS = ("rank_no_fusion", *SCORE_ONLY)

log = logging.getLogger(__name__)

Build = Callable[[Path], "dict[str, Any] | None"]


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


@dataclass
class Pipeline:
    """One config's run into one output directory: the context every stage function takes.

    Attributes:
        cfg: The validated config.
        out: The run directory (claimed: new, empty or an earlier run of the harness).
        rank_import: A localizer's rank file to import instead of computing ranks
            (``--import NAME=FILE``, SPEC section 12).
        force: Replace the tables of a run directory that measured another localizer set.
        annotations_optional: A config without ``annotations`` is fine (``harness detect``).
        train_sessions: The sessions a learned descriptor trains on (None: every session's
            proposals; ``harness detect``: the map alone).
        executor: Maps independent units (local or Ray).
        timings: Seconds per stage.
        ran: Entries built per stage (0 everywhere on a cached rerun).
        used: Entries read or written per stage (what ``harness gc`` keeps).
        not_described: Frames per session that no ranking reads (not proposed or encoded).
    """

    cfg: Config
    out: Path
    rank_import: ImportSpec | None = None
    force: bool = False
    executor: Any = field(default_factory=LocalExecutor)
    annotations_optional: bool = False
    train_sessions: tuple[str, ...] | None = None
    timings: dict[str, float] = field(default_factory=dict)
    ran: dict[str, int] = field(default_factory=dict)
    used: dict[str, set[str]] = field(default_factory=dict)
    not_described: dict[str, int] = field(default_factory=dict)

    @property
    def localizer_list(self) -> tuple[LocalizerConfig, ...]:
        """The localizers this run measures (SPEC section 11).

        ``--import NAME=FILE`` measures that file alone; otherwise ``[[localizers]]``, or the one
        localizer ``[descriptor]`` defines.
        """
        if self.rank_import is not None:
            return (
                LocalizerConfig(
                    self.rank_import.name,
                    "import",
                    self.cfg.proposals.methods,
                    import_=LocalizerImportConfig(
                        str(self.rank_import.path), self.cfg.import_.score_kind
                    ),
                ),
            )
        return self.cfg.localizer_set()

    @property
    def localizer(self) -> dict[str, Any]:
        """The first localizer's record (its name, kind and source)."""
        return localizer_record(self.localizer_list[0], len(self.localizer_list) > 1)

    @contextlib.contextmanager
    def measuring(self, loc: LocalizerConfig) -> Iterator[None]:
        """Run the stages of ``loc``: ``cfg`` seen with its descriptor and import settings.

        The stage functions read ``[descriptor]`` and ``[import]`` from ``p.cfg``; inside this
        block they read the localizer's. A config without ``[[localizers]]`` is unchanged.
        """
        saved = self.cfg
        cfg = saved
        if loc.descriptor is not None:
            cfg = dataclasses.replace(cfg, descriptor=loc.descriptor)
        if loc.import_ is not None:
            cfg = dataclasses.replace(
                cfg, import_=dataclasses.replace(cfg.import_, score_kind=loc.import_.score_kind)
            )
        self.cfg = cfg
        try:
            yield
        finally:
            self.cfg = saved

    def __post_init__(self) -> None:
        if self.rank_import is not None and not isinstance(self.rank_import, ImportSpec):
            self.rank_import = parse_import_arg(str(self.rank_import))
        # never write into a directory the harness did not create; resolved: remote workers may
        # start elsewhere
        self.out = claim_dir(Path(self.out), "run")
        self.cache = StageCache(self.out / "cache")
        self._lock_depth = 0
        self._lock_cm: Any = None

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the run lock of ``out`` (re-entrant); see :func:`harness.outdirs.run_lock`."""
        if self._lock_depth == 0:
            self._lock_cm = run_lock(self.out)
            self._lock_cm.__enter__()
        self._lock_depth += 1
        try:
            yield
        finally:
            self._lock_depth -= 1
            if self._lock_depth == 0:
                cm, self._lock_cm = self._lock_cm, None
                cm.__exit__(None, None, None)

    def unit(self, stage: str, key_parts: tuple[Any, ...], build: Build) -> Entry:
        """The entry of ``stage`` for ``key_parts``, built here by ``build(tmp)`` unless cached."""
        t0 = time.perf_counter()
        path, ran = self.cache.run(stage, key_parts, build)
        self._count(stage, [(path, ran)], t0)
        return Entry(path, path.name)

    def units(
        self, stage: str, units: list[tuple[tuple[Any, ...], Build]], gpu: bool = False
    ) -> list[Entry]:
        """Entries of independent units of ``stage``, built through the executor (in parallel)."""
        t0 = time.perf_counter()
        res = self.executor.map_units(self.cache, stage, units, gpu=gpu)
        self._count(stage, res, t0)
        return [Entry(Path(p), Path(p).name) for p, _ in res]

    def _count(self, stage: str, res: list[tuple[Path, bool]], t0: float) -> None:
        self.ran[stage] = self.ran.get(stage, 0) + sum(int(r) for _, r in res)
        self.used.setdefault(stage, set()).update(Path(p).name for p, _ in res)
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t0

    def run(self) -> dict[str, Any]:
        """Run every stage under the run lock; write the reports into ``out``.

        Return the run record.
        """
        with self.locked():
            return run_all(self)


# ---------------------------------------------------------------- the stages, in data-flow order


def generate_fixture(p: Pipeline) -> None:
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
    from .fixture import FixtureSpec, generate

    log.info("fixture: generating into %s", root)
    spec = FixtureSpec(
        seed=fx.seed,
        frames=fx.frames,
        width=fx.width,
        height=fx.height,
        objects=fx.objects,
        loop_scale=fx.loop_scale,
        render_scale=fx.render_scale,
    )
    t0 = time.perf_counter()
    try:
        generate(root, spec, formats=fx.formats or None)
    except ValueError as err:
        raise ConfigError(f"[fixture] {err}") from None
    p.timings["fixture"] = time.perf_counter() - t0
    if p.cfg.annotations is not None and not p.cfg.annotations.exists():
        p.cfg.annotations.parent.mkdir(parents=True, exist_ok=True)
        write_text(p.cfg.annotations, (root / "annotations.csv").read_text())


def check_fixture_spec(p: Pipeline) -> None:
    """An existing generated fixture must be the one ``[fixture]`` describes.

    Raises:
        ConfigError: it was generated with other settings (naming them); it is never replaced
            silently: the message says to remove it so that the next run generates it again.
    """
    from .fixture.generate import read_spec

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


def check_names(p: Pipeline) -> None:
    """Registry names of the config, checked before the fixture is generated or anything read.

    A descriptor registered at run time counts.

    Raises:
        ConfigError: An unknown descriptor or log format, naming the known ones.
    """
    from .descriptors import REGISTRY
    from .ingest.logs import known_formats

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


def preflight(p: Pipeline) -> None:
    """Every input the config names checked before any stage runs (nothing half done).

    Every session's log (present, readable, of a known format, an NCLT session's camera), the
    annotation file and a proposal table.

    Raises:
        HarnessError: Naming the key or the file and what is wrong.
    """
    from .ingest.logs import detect_format
    from .inputs import check_input

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


def ingest_logs(p: Pipeline) -> dict[str, Entry]:
    """Logs -> one ingest entry per session (``frames.parquet``, images, ``ingest_report.json``)."""
    units: list[tuple[tuple[Any, ...], Build]] = [
        (keys.ingest(p.cfg, sc), partial(ingest_session, sc, p.cfg.ingest)) for sc in p.cfg.sessions
    ]
    return dict(zip([sc.name for sc in p.cfg.sessions], p.units("ingest", units), strict=True))


def frame_table(p: Pipeline, ingested: dict[str, Entry]) -> Table:
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


def annotation_table(p: Pipeline, frames: Table) -> Table:
    """The annotation file, checked against the frames; its key is the file's content hash."""
    if p.cfg.annotations is None:  # harness detect without annotations: no frame is annotated
        return Table(validate_annotations(pd.DataFrame(columns=COLUMNS), None, "none"), "none")
    path = p.cfg.annotations
    if p.annotations_optional:  # harness detect: the rows of the sessions it reads
        every = load_annotations(path)
        names = {s.name for s in p.cfg.sessions}
        mine = every[every["session"].isin(names)].reset_index(drop=True)
        return Table(validate_annotations(mine, frames.df, str(path)), content_sha(path))
    return Table(load_annotations(path, frames.df), content_sha(path))


def query_pairs(p: Pipeline, frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> a reference viewpoint per query frame and season (SPEC 4)."""
    queries = ann.df if p.cfg.pairs.queries == "annotated" else None
    build = partial(write_pairs, frames.df, p.cfg.pairs, p.cfg.seasons(), queries)
    entry = p.unit("pairs", keys.pairs(p.cfg, frames.key, ann.key), build)
    return Table(read_cached_parquet(entry.path / "pairs.parquet"), entry.key)


def session_proposals(
    p: Pipeline, frames: Table, pairs: Table, ingested: dict[str, Entry]
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


def descriptor_model(p: Pipeline, frames: Table, props: dict[str, Table]) -> Entry:
    """Proposals -> the trained descriptor model (empty for descriptors that do not train)."""
    trains = make_descriptor(p.cfg.descriptor).needs_training
    if p.train_sessions is not None:
        props = {s: t for s, t in props.items() if s in p.train_sessions}
    rows = (
        pd.concat([t.df for t in props.values()], ignore_index=True) if trains else pd.DataFrame()
    )
    build = partial(train_model, p.cfg.descriptor, frames.df, rows)
    return p.unit("model", keys.model(p.cfg, trains, [t.key for t in props.values()]), build)


def descriptor_projection(
    p: Pipeline, frames: Table, pairs: Table, props: dict[str, Table], model: Entry
) -> Entry | None:
    """Model -> the compact-descriptor projection (``[projection] dim > 0``).

    Fitted on the reference sessions.

    The reference sessions are those some pair ranks against; None when the projection is off.
    """
    if p.cfg.projection.dim == 0:
        return None
    refs = sorted(set(pairs.df["r_session"]))
    rows = pd.concat([props[s].df for s in refs], ignore_index=True)
    build = partial(
        fit_projection_unit, p.cfg.descriptor, p.cfg.projection, model.path, frames.df, rows
    )
    return p.unit(
        "projection", keys.projection(p.cfg, model.key, [props[s].key for s in refs]), build
    )


def session_descriptors(
    p: Pipeline,
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
    dc = p.cfg.descriptor
    units: list[tuple[tuple[Any, ...], Build]] = []
    spans = {}
    for sc in p.cfg.sessions:
        rows, fr = props[sc.name].df, frames.df[frames.df["session"] == sc.name]
        utimes = np.unique(rows["utime"].to_numpy())
        shards = [
            utimes[i : i + dc.shard_frames] for i in range(0, len(utimes), max(1, dc.shard_frames))
        ]
        spans[sc.name] = (len(units), len(units) + len(shards))
        for si, ut in enumerate(shards):
            build = partial(
                encode_shard,
                dc,
                model.path,
                projection.path if projection else None,
                fr,
                rows[rows["utime"].isin(ut)],
                f"{sc.name} [{si + 1}/{len(shards)}]",
            )
            key = keys.descriptor_shard(
                p.cfg,
                props[sc.name].key,
                model.key,
                [int(u) for u in ut],
                projection.key if projection else None,
            )
            units.append((key, build))
    shards_done = p.units("descriptor_shards", units, gpu=True)
    out = {}
    for sc in p.cfg.sessions:
        parts = shards_done[slice(*spans[sc.name])]
        build = partial(combine_shards, dc, props[sc.name].df, [e.path for e in parts])
        out[sc.name] = p.unit(
            "descriptors",
            keys.descriptors(p.cfg, props[sc.name].key, model.key, [e.key for e in parts]),
            build,
        )
    return out


def ranks_device(p: Pipeline) -> str:
    """The exact engine's device: CUDA when ``[descriptor] device`` allows it and one is present."""
    import torch

    rc, dev = p.cfg.retrieval, p.cfg.descriptor.device
    return (
        "cuda"
        if rc.engine == "exact" and dev in ("auto", "cuda") and torch.cuda.is_available()
        else "cpu"
    )


def query_ranks(p: Pipeline, frames: Table, pairs: Table, described: dict[str, Entry]) -> RankTable:
    """Pairs + descriptors -> the rank of each query subimage's ground-truth place (SPEC section 6).

    Units: (reference session, chunk of ``query_frames_per_shard`` pairs); one engine per
    proposal method inside each. With ``rank_import`` the ranks come from the user's file.
    """
    rc, dkeys = p.cfg.retrieval, {s: e.key for s, e in described.items()}
    paths, device = {s: e.path for s, e in described.items()}, ranks_device(p)
    units: list[tuple[tuple[Any, ...], Build]] = []
    unit_ref = []
    step = max(1, rc.query_frames_per_shard)
    for ref in [s.name for s in p.cfg.sessions]:
        sub = pairs.df[pairs.df["r_session"] == ref].reset_index(drop=True)
        for c0 in range(0, max(len(sub), 1), step):
            chunk = sub.iloc[c0 : c0 + step]
            build = partial(
                _write_ranks, rc, p.cfg.pairs.max_yaw_diff_deg, chunk, ref, paths, frames.df, device
            )
            units.append((keys.ranks_unit(p.cfg, ref, pairs.key, dkeys, c0, len(chunk)), build))
            unit_ref.append(ref)
    parts: list[pd.DataFrame] = []
    counts: dict[str, dict[str, int]] = {}
    for ref, entry in zip(unit_ref, p.units("ranks", units, gpu=True), strict=True):
        parts.append(read_cached_parquet(entry.path / "ranks.parquet"))
        c = counts.setdefault(ref, {})
        for k, v in p.cache.manifest("ranks", entry.key)["info"].items():
            c[k] = c.get(k, 0) + v
    parts = [d for d in parts if len(d)]
    df = (
        pd.concat(parts, ignore_index=True).sort_values(SORT_RANKS).reset_index(drop=True)
        if parts
        else pd.DataFrame()
    )
    return RankTable(df, stable_hash(*keys.ranks(p.cfg, pairs.key, dkeys)), counts)


SORT_RANKS = ["q_session", "q_camera", "q_utime", "r_session", "method", "box_id"]


def _write_ranks(
    rc: Any,
    max_yaw_deg: float,
    pairs: pd.DataFrame,
    ref: str,
    descriptors: dict[str, Path],
    frames: pd.DataFrame,
    device: str,
    tmp: Path,
) -> dict[str, int]:
    """One ranking unit (:func:`harness.retrieval.rank_reference`) into ``tmp/ranks.parquet``."""
    df, counts = rank_reference(rc, max_yaw_deg, pairs, ref, descriptors, frames, device)
    write_parquet(tmp / "ranks.parquet", df)
    return counts


def imported_ranks(
    p: Pipeline, frames: Table, pairs: Table, props: dict[str, Table], spec: ImportSpec
) -> RankTable:
    """Ranks from a user's localizer (``--import NAME=FILE`` or an ``import`` localizer).

    Checked against the run (SPEC 12): every row must be a proposal of the run and match a pair;
    a query image of the pairs without any row is an error unless ``[import]
    allow_unranked_images`` (then it is counted).
    """
    from .retrieval.imported import write_imported_ranks

    if not Path(spec.path).is_file():
        raise RetrievalError(f"{spec.path}: --import file not found (localizer {spec.name!r})")
    allprops = pd.concat([t.df for t in props.values()], ignore_index=True)
    build = partial(
        write_imported_ranks,
        spec,
        pairs.df,
        frames.df,
        allprops,
        p.cfg.retrieval.gt_radius_m,
        p.cfg.pairs.max_yaw_diff_deg,
        p.cfg.import_.score_kind,
    )
    key = keys.ranks_import(
        p.cfg, spec.name, content_sha(spec.path), pairs.key, [t.key for t in props.values()]
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
    p: Pipeline, ranks: RankTable, frames: Table, ann: Table, fusion: FusionConfig | None = None
) -> Table:
    """Ranks + annotations -> a sample per fused box with each method's LoC (SPEC 7-8)."""
    fc = fusion or p.cfg.fusion
    cfg = p.cfg if fusion is None else dataclasses.replace(p.cfg, fusion=fc)
    build = partial(write_samples, ranks.df, frames.df, ann.df, fc)
    entry = p.unit("samples", keys.samples(cfg, ranks.key, ann.key), build)
    return Table(read_cached_parquet(entry.path / "samples.parquet"), entry.key)


def change_tables(p: Pipeline, blocks: list[Block], frames: Table, ann: Table) -> Reports:
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


# ---------------------------------------------------------------- localizers (SPEC section 11)


@dataclass
class Measured:
    """One localizer's ranks, the fusion methods it can have, and what its tables must say."""

    loc: LocalizerConfig
    ranks: RankTable
    fusion: FusionConfig
    notes: list[str] = field(default_factory=list)


def localizer_record(loc: LocalizerConfig, full: bool = True) -> dict[str, Any]:
    """What ``run.json`` and the page say of a localizer: name, kind, source."""
    if loc.import_ is not None:
        path = Path(loc.import_.file)
        return {
            "name": loc.name,
            "kind": "import",
            "file": str(path.resolve()),
            "sha256": content_sha(path) if path.is_file() else None,
            "score_kind": loc.import_.score_kind,
            **({"proposals": list(loc.proposals)} if full else {}),
        }
    rec: dict[str, Any] = {"name": loc.name, "kind": loc.kind}
    if full:
        rec["proposals"] = list(loc.proposals)
        if loc.descriptor is not None:
            rec["descriptor"] = loc.descriptor.name
        if loc.bovw is not None:
            rec["bovw"] = dataclasses.asdict(loc.bovw)
    return rec


def localizer_proposals(
    p: Pipeline, loc: LocalizerConfig, props: dict[str, Table]
) -> dict[str, Table]:
    """Each session's proposals cut to the localizer's methods (as they are when it uses all)."""
    if set(loc.proposals) == set(p.cfg.proposals.methods):
        return props
    return {
        s: Table(
            t.df[t.df["method"].isin(loc.proposals)].reset_index(drop=True),
            keys.subset(t.key, loc.proposals),
        )
        for s, t in props.items()
    }


def bovw_vocabulary(
    p: Pipeline, loc: LocalizerConfig, frames: Table, pairs: Table, props: dict[str, Table]
) -> Entry:
    """Reference-session subimages -> a bag-of-words vocabulary and its IDF (SPEC section 11)."""
    from .retrieval.bovw import train_vocabulary

    assert loc.bovw is not None
    refs = sorted(set(pairs.df["r_session"]))
    rows = pd.concat([props[s].df for s in refs], ignore_index=True)
    build = partial(train_vocabulary, loc.bovw, frames.df, rows)
    return p.unit("bovw_vocab", keys.bovw_vocab(loc.bovw, [props[s].key for s in refs]), build)


def bovw_words(
    p: Pipeline, loc: LocalizerConfig, frames: Table, props: dict[str, Table], vocab: Entry
) -> tuple[dict[str, Entry], int]:
    """Each session's word vectors (``words.npz`` + ``index.parquet``), in resumable shards.

    Returns:
        The entries, and how many subimages had no feature (no vector, counted).
    """
    from .retrieval.bovw import combine_word_shards, encode_words

    bc = loc.bovw
    assert bc is not None
    units: list[tuple[tuple[Any, ...], Build]] = []
    spans = {}
    for sc in p.cfg.sessions:
        rows, fr = props[sc.name].df, frames.df[frames.df["session"] == sc.name]
        utimes = np.unique(rows["utime"].to_numpy())
        shards = [utimes[i : i + bc.shard_frames] for i in range(0, len(utimes), bc.shard_frames)]
        spans[sc.name] = (len(units), len(units) + len(shards))
        for si, ut in enumerate(shards):
            build = partial(
                encode_words,
                bc,
                vocab.path,
                fr,
                rows[rows["utime"].isin(ut)].reset_index(drop=True),
                f"{loc.name} {sc.name} [{si + 1}/{len(shards)}]",
            )
            key = keys.bovw_shard(vocab.key, props[sc.name].key, [int(u) for u in ut])
            units.append((key, build))
    done = p.units("bovw_shards", units)
    nofeat = sum(
        int(p.cache.manifest("bovw_shards", e.key)["info"].get("no_feature_subimages", 0))
        for e in done
    )
    out = {}
    for sc in p.cfg.sessions:
        parts = done[slice(*spans[sc.name])]
        build = partial(combine_word_shards, [e.path for e in parts])
        out[sc.name] = p.unit(
            "bovw_words",
            keys.bovw_words(vocab.key, props[sc.name].key, [e.key for e in parts]),
            build,
        )
    return out, nofeat


def localizer_ranks(
    p: Pipeline, loc: LocalizerConfig, frames: Table, pairs: Table, props: dict[str, Table]
) -> RankTable:
    """One localizer's rank rows: its engine over its proposals (SPEC sections 6, 11, 12)."""
    mine = localizer_proposals(p, loc, props)
    with p.measuring(loc):
        if loc.import_ is not None:
            spec = ImportSpec(loc.name, Path(loc.import_.file))
            return imported_ranks(p, frames, pairs, mine, spec)
        if loc.bovw is not None:
            vocab = bovw_vocabulary(p, loc, frames, pairs, mine)
            words, nofeat = bovw_words(p, loc, frames, mine, vocab)
            ranks = query_ranks(p, frames, pairs, words)
            ranks.counts["bovw"] = {"no_feature_subimages": nofeat}
            return ranks
        model = descriptor_model(p, frames, mine)
        projection = descriptor_projection(p, frames, pairs, mine, model)
        described = session_descriptors(p, frames, mine, model, projection)
        return query_ranks(p, frames, pairs, described)


def localizer_fusion(
    p: Pipeline, loc: LocalizerConfig, ranks: RankTable, n_images: int
) -> tuple[FusionConfig, list[str]]:
    """The fusion methods a localizer can have, and the notes its tables carry.

    A localizer without a relevance score (an imported list without ``scores``) gets no score
    method (never NaN rows without a word); lost images and truncated lists are noted.
    """
    notes: list[str] = []
    fc = p.cfg.fusion
    info = ranks.counts.get("import", {})
    has_d = loc.import_ is None or bool(info.get("has_scores"))
    if not has_d:
        dropped = [m for m in SCORE_ONLY if m in fc.methods]
        kept = tuple(m for m in fc.methods if m not in dropped)
        if dropped and kept:
            fc = dataclasses.replace(fc, methods=kept)
        if dropped:
            notes.append(
                f"NOTE: {', '.join(dropped)} not computed: localizer {loc.name} gives ranked "
                "lists without scores, so it has no relevance score d (SPEC sections 11-12)."
            )
    lost = int(info.get("unranked_query_images", 0))
    if lost:
        notes.append(
            f"NOTE: {lost} of {n_images} query images have no row from localizer {loc.name} "
            "and are left out of every table ([import] allow_unranked_images = true)."
        )
    inexact = int(info.get("gt_missing_from_truncated_list", 0))
    if inexact:
        notes.append(
            f"NOTE: {inexact} of {len(ranks.df)} query subimages of localizer {loc.name} have a "
            "truncated list without their place: their rank is a bound (exact = False)."
        )
    nofeat = int(ranks.counts.get("bovw", {}).get("no_feature_subimages", 0))
    if nofeat:
        notes.append(
            f"NOTE: {nofeat} subimages had no local feature under localizer {loc.name}: they "
            "are neither queries nor database rows of its engine (SPEC section 11)."
        )
    return fc, notes


IMAGE_KEY = ["q_session", "q_camera", "q_utime", "r_session"]


def common_images(p: Pipeline, measured: list[Measured], pairs: Table) -> str | None:
    """Score every localizer on the same query images (SPEC section 11).

    A query image of the pairs that some localizer did not rank is an error naming the
    localizer and the image, unless ``[import] allow_unranked_images``: then it is left out of
    every localizer's ranks, and the returned note says how many.

    Raises:
        RetrievalError: an unranked image (not allowed).
    """
    all_images = pd.MultiIndex.from_frame(pairs.df[IMAGE_KEY])
    keep = np.ones(len(all_images), bool)
    first_missing: tuple[str, Any] | None = None
    for m in measured:
        got = pd.MultiIndex.from_frame(m.ranks.df[IMAGE_KEY].drop_duplicates())
        has = all_images.isin(got)
        if first_missing is None and not has.all():
            first_missing = (m.loc.name, all_images[np.flatnonzero(~has)[0]])
        keep &= has
    if keep.all():
        return None
    lost = int((~keep).sum())
    assert first_missing is not None
    name, ex = first_missing
    if not p.cfg.import_.allow_unranked_images:
        raise RetrievalError(
            f"localizer {name!r} ranks no subimage of query image {ex[0]}/{ex[1]}/{ex[2]} -> "
            f"{ex[3]} ({lost} of {len(all_images)} query images lack some localizer's rank); "
            "every localizer is scored on the same images: set [import] allow_unranked_images "
            "= true to leave them out of every table (counted)"
        )
    kept = pd.MultiIndex.from_frame(pairs.df[IMAGE_KEY][keep])
    for m in measured:
        df = m.ranks.df
        sel = pd.MultiIndex.from_frame(df[IMAGE_KEY]).isin(kept)
        if not sel.all():
            m.ranks = RankTable(
                df[sel].reset_index(drop=True),
                stable_hash("common-images", m.ranks.key, int((~sel).sum())),
                m.ranks.counts,
            )
    return (
        f"NOTE: {lost} of {len(all_images)} query images lack a rank from at least one "
        f"localizer (e.g. {name}: {ex[0]}/{ex[1]}/{ex[2]}) and are left out of every row "
        "([import] allow_unranked_images = true)."
    )


def across_localizers(measured: list[Measured]) -> RankTable:
    """Every localizer's rank rows as one list of original boxes (SPEC section 11).

    An original box is the pair (localizer, box): its method becomes ``localizer:method``, and
    ``d`` is dropped (scores of different localizers are not comparable).
    """
    parts = [
        m.ranks.df.assign(method=m.loc.name + ":" + m.ranks.df["method"].astype(str), d=np.nan)
        for m in measured
    ]
    df = pd.concat(parts, ignore_index=True).sort_values(SORT_RANKS).reset_index(drop=True)
    return RankTable(df, stable_hash("all-localizers", [m.ranks.key for m in measured]), {})


# ---------------------------------------------------------------- the chain


def until_pairs(p: Pipeline) -> tuple[dict[str, Entry], Table, Table, Table]:
    """Fixture (if configured), ingest, frames, annotations and pairs.

    Returns:
        (ingest entries, frames, annotations, pairs).
    """
    check_names(p)
    generate_fixture(p)
    preflight(p)
    ingested = ingest_logs(p)
    frames = frame_table(p, ingested)
    ann = annotation_table(p, frames)
    return ingested, frames, ann, query_pairs(p, frames, ann)


def until_ranks(
    p: Pipeline, check: bool = True
) -> tuple[dict[str, Entry], Table, Table, Table, list[Measured]]:
    """Every stage up to the ranks of every localizer (computed, or imported).

    With ``check``, inputs that can only give NaN tables are refused before any proposal work.
    Proposals are computed once and shared by the localizers that use the same method.

    Returns:
        (ingest entries, frames, annotations, pairs, one :class:`Measured` per localizer).
    """
    ingested, frames, ann, pairs = until_pairs(p)
    if check:
        check_inputs(p, ann, pairs)
    props = session_proposals(p, frames, pairs, ingested)
    measured = []
    for loc in p.localizer_list:
        ranks = localizer_ranks(p, loc, frames, pairs, props)
        if not len(ranks.df):
            raise RetrievalError(f"localizer {loc.name}: no query subimage got a rank")
        fusion, notes = localizer_fusion(p, loc, ranks, len(pairs.df))
        measured.append(Measured(loc, ranks, fusion, notes))
    return ingested, frames, ann, pairs, measured


def run_all(p: Pipeline) -> dict[str, Any]:
    """The whole chain into ``p.out``: stages, reports, ``run.json`` (and ``report.html``).

    Returns:
        The run record (``run.json``'s content plus ``table`` and ``reports``).
    """
    t0 = time.perf_counter()
    check_localizer_set(p)
    ingested, frames, ann, pairs, measured = until_ranks(p)
    blocks, keys_ = [], {}
    shared = common_images(p, measured, pairs) if len(measured) > 1 else None
    n_samples = 0
    for m in measured:
        samples = fused_samples(p, m.ranks, frames, ann, m.fusion)
        notes = m.notes + ([shared] if shared else [])
        blocks.append(
            Block(m.loc.name, samples.df, m.ranks.df, ordered_methods(m.fusion.methods), notes)
        )
        keys_[m.loc.name] = {"ranks": m.ranks.key, "samples": samples.key}
        n_samples += len(samples.df)
    if len(measured) > 1:
        ranks_all = across_localizers(measured)
        fc = dataclasses.replace(
            p.cfg.fusion, methods=tuple(x for x in p.cfg.fusion.methods if x not in NOT_ACROSS)
        )
        samples = fused_samples(p, ranks_all, frames, ann, fc)
        blocks.append(
            Block(
                ALL_LOCALIZERS,
                samples.df,
                None,
                ordered_methods(fc.methods),
                [shared] if shared else [],
            )
        )
        keys_[ALL_LOCALIZERS] = {"ranks": ranks_all.key, "samples": samples.key}
        n_samples += len(samples.df)
    reports = change_tables(p, blocks, frames, ann)
    record = run_record(
        p,
        ingested,
        frames,
        ann,
        pairs,
        measured,
        keys_,
        n_samples,
        reports,
        time.perf_counter() - t0,
    )
    write_json(p.out / "run.json", record)
    if p.cfg.report.html:
        from .report_html import write_html_report

        t_html = time.perf_counter()
        record["report_html"] = str(write_html_report(p.out))
        p.timings["report_html"] = time.perf_counter() - t_html
    record["table"] = reports.tables["I"]
    record["reports"] = reports
    return record


def check_localizer_set(p: Pipeline) -> None:
    """Refuse to replace the tables of a run that measured another localizer set, unless ``force``.

    Raises:
        HarnessError: ``out/run.json`` names other localizers; the message names both sets.
    """
    if p.force or not (p.out / "run.json").exists():
        return
    try:
        rec = read_run_record(p.out)
    except HarnessError:
        return  # a damaged record is rewritten by this run
    config = rec.get("config")
    listed = rec.get("localizers")
    before = [
        str(loc.get("name"))
        for loc in (listed if isinstance(listed, list) else [])
        if isinstance(loc, dict)
    ]
    if not before and isinstance(config, dict):
        before = [str(config.get("descriptor", {}).get("name", "?"))]
    now = [loc.name for loc in p.localizer_list]
    if before != now:
        raise HarnessError(
            f"{p.out}: holds the tables of localizer {', '.join(before)}; this run measures "
            f"{', '.join(now)}; pass --force to replace them, or choose another --out"
        )


def check_inputs(p: Pipeline, ann: Table, pairs: Table) -> None:
    """Refuse, before any proposal or descriptor work, inputs that can only give NaN tables."""
    if not (ann.df["status"] == "change").any():
        raise HarnessError(
            f"{p.cfg.annotations}: no frame is annotated 'change', so no split has a "
            "positive and every AP "
            "would be NaN; annotate at least one change box"
        )
    if not len(pairs.df):
        raise HarnessError(
            "no query frame found a reference frame; check [pairs] and the annotations"
        )


def run_record(
    p: Pipeline,
    ingested: dict[str, Entry],
    frames: Table,
    ann: Table,
    pairs: Table,
    measured: list[Measured],
    block_keys: dict[str, dict[str, str]],
    n_samples: int,
    reports: Reports,
    seconds: float,
) -> dict[str, Any]:
    """What ``run.json`` records.

    Config, versions, timings, counts, keys, warnings, cache entries. With several localizers the
    rank counters and keys are given per localizer (``keys.localizers``).
    """
    multi = len(measured) > 1
    first = measured[0]
    rank_counts: Any = (
        {m.loc.name: m.ranks.counts for m in measured} if multi else first.ranks.counts
    )
    unranked = sum(
        int(c.get("unranked_query_images", 0))
        for m in measured
        for c in m.ranks.counts.values()
        if isinstance(c, dict)
    )
    return {
        "config": asdict(p.cfg),
        "versions": _versions(),
        "seed": p.cfg.seed,
        "argv": sys.argv,
        "localizers": [localizer_record(m.loc, multi) for m in measured],
        "timings_s": {k: round(v, 3) for k, v in p.timings.items()},
        "total_s": round(seconds, 3),
        "stage_units_run": p.ran,
        "executor": p.executor.describe(),
        "counts": {
            "frames": len(frames.df),
            "annotated_frames": int(
                ann.df[["session", "camera", "utime"]].drop_duplicates().shape[0]
            ),
            "pairs": len(pairs.df),
            "frames_not_described": dict(sorted(p.not_described.items())),
            "ranked_subimages": sum(len(m.ranks.df) for m in measured),
            "unranked_query_images": unranked,
            "samples": n_samples,
            "rank_counts": rank_counts,
        },
        "keys": {
            "frames": frames.key,
            "pairs": pairs.key,
            **block_keys[first.loc.name],
            **({"localizers": block_keys} if multi else {}),
        },
        "localization": reports.localization.to_dict(orient="records"),
        "warnings": reports.warnings,
        "ingest": {
            name: ingest_summary(e.path / "ingest_report.json") for name, e in ingested.items()
        },
        "cache_entries": {stage: sorted(keys_) for stage, keys_ in sorted(p.used.items())},
    }


# ---------------------------------------------------------------- helpers


def ingest_summary(path: Path) -> dict[str, Any]:
    """What run.json keeps of a session's ingest report: frames written, drops, pose frames."""
    rep = json.loads(path.read_text())
    return {
        k: rep[k]
        for k in ("format", "frames_written", "dropped", "pose_frames", "salvaged")
        if k in rep
    }


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    import cv2
    import torch

    def ver(dist: str) -> str:
        try:
            return version(dist)
        except PackageNotFoundError:
            return "?"

    return {
        "dbl-harness": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "pandas": pd.__version__,
        "torch": torch.__version__,
        "opencv": cv2.__version__,
        "rosbags": ver("rosbags"),
        "mcap": ver("mcap"),
        "platform": platform.platform(),
    }


def reproduce(
    cfg: Config,
    out: Path,
    rank_import: ImportSpec | None = None,
    executor: Any = None,
    force: bool = False,
) -> dict[str, Any]:
    """Run the whole pipeline for ``cfg`` into ``out`` (``executor``: local by default)."""
    return Pipeline(
        cfg, Path(out), rank_import=rank_import, executor=executor or LocalExecutor(), force=force
    ).run()


def load_run(out: Path) -> dict[str, Any]:
    """The ``run.json`` of a finished run in ``out``."""
    return json.loads((Path(out) / "run.json").read_text())

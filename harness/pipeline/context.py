"""The run context every stage takes (:class:`Context`) and the run's localizers (method §11).

A :class:`Context` is the :class:`harness.runtime.stage.Units` a stage function builds its
entries in; the outputs' records (``Entry``, ``Table``, ``RankTable``) are in
:mod:`harness.runtime.stage`. The chain is :mod:`harness.pipeline.chain`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.config.schema import Config
from harness.descriptors import stage as descriptor_stage
from harness.descriptors.config import DescriptorConfig
from harness.localizers.config import LocalizerConfig, LocalizerImportConfig
from harness.localizers.kinds import LOCALIZER_KINDS
from harness.pairs.modes import kind_of
from harness.retrieval import stage as retrieval_stage
from harness.retrieval.config import RetrievalConfig
from harness.retrieval.import_file import ImportSpec, parse_import_arg
from harness.retrieval.units import RankSettings
from harness.runtime.cache import StageCache, content_sha
from harness.runtime.executors import LocalExecutor
from harness.runtime.hardware import rank_precision
from harness.runtime.outdirs import claim_dir, run_lock
from harness.runtime.stage import Build, CombineUnit, Entry, RankTable, ShardUnit, Table

log = logging.getLogger(__name__)


@dataclass
class Context:
    """One config's run into one output directory: the context every stage function takes.

    :class:`harness.pipeline.chain.Pipeline` adds ``run`` (the chain).

    Attributes:
        cfg: The validated config.
        out: The run directory (claimed: new, empty or an earlier run of the harness).
        rank_import: A localizer's rank file to import instead of computing ranks
            (``--import NAME=FILE``, method §12).
        force: Replace the tables of a run directory that measured another localizer set.
        annotations_optional: A config without ``annotations`` is fine (``harness detect``).
        train_sessions: The sessions a learned descriptor trains on (None: every session's
            proposals; ``harness detect``: the map alone).
        executor: Maps independent units (local or Ray).
        timings: Seconds per stage.
        ran: Entries built per stage (0 everywhere on a cached rerun).
        used: Entries read or written per stage (what ``harness gc`` keeps).
        not_described: Frames per session that no ranking reads (not proposed or encoded).
        pairing: How the pairs were made (``[pairs] by``) and, by retrieval where poses exist,
            how often they agree with the pose pairs (method §13.2).
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
    # every entry the run used, in order (stage, entry directory): what a localizer cost
    trail: list[tuple[str, Path]] = field(default_factory=list)
    not_described: dict[str, int] = field(default_factory=dict)
    pairing: dict[str, Any] = field(default_factory=dict)

    @property
    def localizer_list(self) -> tuple[LocalizerConfig, ...]:
        """The localizers this run measures (method §11).

        ``--import NAME=FILE`` measures that file alone; otherwise ``[[localizers]]``, or the one
        localizer ``[descriptor]`` defines.
        """
        if self.rank_import is not None:
            return (
                LocalizerConfig(
                    self.rank_import.name,
                    "import",
                    self.cfg.proposals.methods,
                    options=LocalizerImportConfig(
                        str(self.rank_import.path), self.cfg.import_.score_kind
                    ),
                ),
            )
        return self.cfg.localizer_set()

    @property
    def localizer(self) -> dict[str, Any]:
        """The first localizer's record (its name, kind and source)."""
        return localizer_record(self.localizer_list[0], len(self.localizer_list) > 1)

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
        """Hold the run lock of ``out`` (re-entrant): :func:`harness.runtime.outdirs.run_lock`."""
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

    def sharded(self, stages: tuple[str, str], props: dict[str, Table], shard_frames: int,
                shard: ShardUnit, combine: CombineUnit, gpu: bool = False,
                ) -> tuple[dict[str, Entry], list[Entry]]:  # fmt: skip
        """Shard, build, combine: a per-session stage cached in shards of frames.

        Each session's proposal rows are cut into shards of ``shard_frames`` frames (in time
        order); ``shard(session, rows, utimes, label)`` gives each shard's key and build, run as
        units of ``stages[0]`` through the executor (an interrupted stage resumes at the next
        unfinished shard); ``combine(session, its shard entries)`` gives the session's entry of
        ``stages[1]``, built one session at a time.

        Returns:
            Session name -> its combined entry, and every shard entry (in session order).
        """
        units: list[tuple[tuple[Any, ...], Build]] = []
        spans = {}
        step = max(1, shard_frames)
        for sc in self.cfg.sessions:
            rows = props[sc.name].df
            utimes = np.unique(rows["utime"].to_numpy())
            cuts = [utimes[i : i + step] for i in range(0, len(utimes), step)]
            spans[sc.name] = (len(units), len(units) + len(cuts))
            for i, ut in enumerate(cuts):
                label = f"{sc.name} [{i + 1}/{len(cuts)}]"
                mine = rows[rows["utime"].isin(ut)]
                units.append(shard(sc.name, mine, [int(u) for u in ut], label))
        done = self.units(stages[0], units, gpu=gpu)
        out = {s: self.unit(stages[1], *combine(s, done[slice(*ab)])) for s, ab in spans.items()}
        return out, done

    # ------------------------------------------ the stages a localizer kind calls, with the run's
    # sections (:class:`harness.localizers.kinds.LocalizerRun`)

    @property
    def descriptor_device(self) -> str:
        """The run's ``[descriptor] device``: where a kind without a descriptor of its own ranks."""
        return self.cfg.descriptor.device

    def descriptor_model(
        self, dc: DescriptorConfig, frames: Table, props: dict[str, Table]
    ) -> Entry:
        """Proposals -> the trained model of ``dc``, on the run's training sessions' proposals."""
        if self.train_sessions is not None:
            props = {s: t for s, t in props.items() if s in self.train_sessions}
        return descriptor_stage.descriptor_model(self, dc, frames, props)

    def descriptor_projection(
        self,
        dc: DescriptorConfig,
        frames: Table,
        pairs: Table,
        props: dict[str, Table],
        model: Entry,
    ) -> Entry | None:
        """Model -> the compact-descriptor projection under ``[projection]`` (None when off)."""
        pc = self.cfg.projection
        return descriptor_stage.descriptor_projection(self, dc, pc, frames, pairs, props, model)

    def query_ranks(
        self,
        frames: Table,
        pairs: Table,
        described: dict[str, Entry],
        rc: RetrievalConfig,
        device: str = "auto",
        precision: str = "fp32",
    ) -> RankTable:
        """Pairs + descriptors -> the rank of each query subimage's true place (method §6).

        ``rc``: the ``[retrieval]`` to rank under (the run's, or ``gt_radius_also``'s).
        ``device``: the descriptor's (``[descriptor] device``); the exact engine runs on CUDA
        where it allows and one is present. ``precision``: the descriptor's, for the exact
        engine's candidate product (:func:`harness.runtime.hardware.rank_precision`). By
        retrieval (method §13.2) the place is ``[pairs] place_frames`` frames each side.
        """
        pc = self.cfg.pairs
        how = RankSettings(
            rc,
            pc.max_yaw_diff_deg,
            ranks_device(rc, device),
            pc.place_frames if kind_of(pc.by) != "pose" else None,
            rank_precision(precision) if rc.engine == "exact" else "fp32",
        )
        refs = [s.name for s in self.cfg.sessions]
        return retrieval_stage.rank_queries(self, how, refs, frames, pairs, described)

    def imported_ranks(
        self,
        frames: Table,
        pairs: Table,
        props: dict[str, Table],
        spec: ImportSpec,
        score_kind: str,
        rc: RetrievalConfig,
    ) -> RankTable:
        """Ranks from a user's file, scored as ``score_kind``.

        :func:`harness.retrieval.stage.imported_ranks` under the run's ``[import]`` and heading
        limit.
        """
        imp = dataclasses.replace(self.cfg.import_, score_kind=score_kind)
        yaw = self.cfg.pairs.max_yaw_diff_deg
        return retrieval_stage.imported_ranks(self, rc, imp, yaw, frames, pairs, props, spec)

    def _count(self, stage: str, res: list[tuple[Path, bool]], t0: float) -> None:
        self.ran[stage] = self.ran.get(stage, 0) + sum(int(r) for _, r in res)
        self.used.setdefault(stage, set()).update(Path(p).name for p, _ in res)
        self.trail.extend((stage, Path(p)) for p, _ in res)
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t0


def ranks_device(rc: RetrievalConfig, dev: str) -> str:
    """The exact engine's device: CUDA when ``dev`` (the descriptor's) allows it and one exists."""
    import torch

    return (
        "cuda"
        if rc.engine == "exact" and dev in ("auto", "cuda") and torch.cuda.is_available()
        else "cpu"
    )


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
        rec.update(LOCALIZER_KINDS[loc.kind].describe(loc.options))
    return rec

"""The pipeline (method §3-10) as a chain of stage calls.

logs -> frames -> pairs -> proposals -> model [-> projection] -> descriptors -> ranks -> samples ->
tables

Each stage is a function of its package (``harness/<stage>/stage.py``) taking typed inputs (the
run, its config sections and the outputs of the stages before it) to a typed output. It builds its
cache key with its package's ``keys.py`` and hands a build function (a module-level function of
the stage's module, bound with :func:`functools.partial`) to the cache: an entry
``<out>/cache/<stage>/<key>/`` is built once, so a rerun with nothing changed does no work, an
interrupted run resumes, and changing one option reruns only what depends on it.
``docs/architecture.md`` draws the chain.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any

from harness.config.schema import Config
from harness.errors import ConfigError, HarnessError, RetrievalError
from harness.ingest.names import session_names
from harness.localizers.config import ALL_LOCALIZERS
from harness.methods import ordered_methods, rules_where
from harness.pairs import keys as pair_keys
from harness.pairs.agreement import pose_agreement
from harness.pairs.modes import PAIRING_MODES, kind_of
from harness.pairs.place import hub_report, no_place_report, unpaired_report
from harness.pairs.pose import build_pairs
from harness.pipeline.across import across_localizers, common_images, localizer_fusion
from harness.pipeline.context import Context
from harness.pipeline.localizer_stages import (
    Measured,
    localizer_ranks,
    measured_costs,
    ranks_at_radius,
    retrieval_ranks,
)
from harness.pipeline.preflight import check_names, generate_fixture, preflight
from harness.pipeline.record import RunOutcome, run_record
from harness.pipeline.stages import (
    annotation_table,
    candidate_table,
    change_tables,
    frame_table,
    fused_samples,
    ingest_logs,
    query_pairs,
    session_proposals,
)
from harness.reports.blocks import Block
from harness.reports.html.page import write_html_report
from harness.retrieval.import_file import ImportSpec
from harness.runtime.cache import write_json
from harness.runtime.executors import LocalExecutor
from harness.runtime.outdirs import read_run_record
from harness.runtime.stage import Entry, Table

#: The chain's own names.
__all__ = [
    "Pipeline",
    "check_inputs",
    "check_localizer_set",
    "load_run",
    "reproduce",
    "run_all",
    "until_pairs",
    "until_ranks",
]

log = logging.getLogger(__name__)

# ---------------------------------------------------------------- the chain


class Pipeline(Context):
    """A run: the :class:`~harness.pipeline.context.Context` every stage takes, and the chain."""

    def run(self) -> dict[str, Any]:
        """Run every stage under the run lock; write the reports into ``out``.

        Return the run record.
        """
        with self.locked():
            return run_all(self)


def until_annotations(p: Context) -> tuple[dict[str, Entry], Table, Table]:
    """Fixture (if configured), ingest, frames and annotations.

    Returns:
        (ingest entries, frames, annotations).
    """
    check_names(p)
    generate_fixture(p)
    preflight(p)
    ingested = ingest_logs(p)
    frames = frame_table(p, ingested)
    return ingested, frames, annotation_table(p, frames)


def until_pairs(p: Context) -> tuple[dict[str, Entry], Table, Table, Table]:
    """Fixture (if configured), ingest, frames, annotations and pairs by pose.

    Raises:
        ConfigError: ``[pairs] by = "retrieval"``: pairs need the descriptors (``rank``,
            ``reproduce`` and ``detect`` make them).

    Returns:
        (ingest entries, frames, annotations, pairs).
    """
    if kind_of(p.cfg.pairs.by) == "retrieval":
        raise ConfigError(
            f"[pairs] by = {p.cfg.pairs.by!r}: the pairs come from the localizer's descriptors; "
            "harness rank, reproduce and detect make them (pairs and proposals alone cannot)"
        )
    ingested, frames, ann = until_annotations(p)
    pairs = query_pairs(p, frames, ann)
    if kind_of(p.cfg.pairs.by) == "declared":
        p.pairing = {"by": p.cfg.pairs.by, "place_frames": p.cfg.pairs.place_frames}
        _pose_agreement(p, frames, ann, pairs)
    return ingested, frames, ann, pairs


def _pose_agreement(p: Context, frames: Table, ann: Table, pairs: Table) -> None:
    """How often pairs not made by pose agree with pose pairs (method §13.2): ``p.pairing``.

    Only where every frame has a pose.
    """
    posed = frames.df[["x", "y", "yaw"]].notna().all(axis=1)
    if posed.all() and len(frames.df):
        queries = ann.df if p.cfg.pairs.queries == "annotated" else None
        by_pose, _ = build_pairs(frames.df, p.cfg.pairs, p.cfg.seasons(), queries)
        within = p.cfg.pairs.max_distance_m or 10.0
        p.pairing["agreement_with_pose_pairs"] = pose_agreement(
            pairs.df, by_pose, frames.df, within
        )


def pairs_by_retrieval(
    p: Context,
    ingested: dict[str, Entry],
    frames: Table,
    ann: Table,
    check: bool = True,
    detect: tuple[str, tuple[str, ...]] | None = None,
) -> tuple[Table, Measured]:
    """Pairs by retrieval with the run's one descriptor localizer, and its ranks (method §13.2).

    Where the paired frames have poses, ``p.pairing`` records how often the retrieval pair lies
    within ``[pairs] max_distance_m`` (10 m when unset) of the pose pair. ``detect``: (the map,
    the query sessions): only those pairs (``harness detect``).
    """
    locs = p.localizer_list
    if len(locs) != 1:
        raise ConfigError(
            f"[pairs] by = 'retrieval' pairs with the run's localizer: one localizer, not "
            f"{len(locs)} ({', '.join(x.name for x in locs)})"
        )
    cand = candidate_table(p, frames, ann)
    if detect is not None:
        sel = (cand.df["r_session"] == detect[0]) & cand.df["q_session"].isin(detect[1])
        cand = Table(
            cand.df[sel].reset_index(drop=True),
            pair_keys.selected("detect-candidates", cand.key, detect[0], detect[1]),
        )
    if check:
        check_inputs(p, ann, cand)
    # a detector pairs with its localizer's proposal methods alone (its own, such as Selective
    # Search, are proposed later, on the frames it reads: not on every candidate map frame)
    only = tuple(locs[0].proposals) if detect is not None else None
    props = session_proposals(p, frames, cand, ingested, methods=only)
    start = len(p.trail)
    pairs, ranks = retrieval_ranks(p, locs[0], frames, cand, props)
    if not len(ranks.df):
        raise RetrievalError(f"localizer {locs[0].name}: no query subimage got a rank")
    p.pairing = {"by": p.cfg.pairs.by, "place_frames": p.cfg.pairs.place_frames}
    names = session_names(p.cfg.sessions)
    summary = p.cache.path("pairs_retrieval", pairs.key) / "summary.json"
    if (blank := no_place_report(summary, names)) is not None:
        p.pairing["no_place"] = blank
    if unpaired := unpaired_report(summary, names):
        p.pairing["unpaired"] = unpaired
    p.pairing["hubs"] = hub_report(pairs.df, frames.df, names)
    _pose_agreement(p, frames, ann, pairs)
    fusion, notes = localizer_fusion(p, locs[0], ranks, len(pairs.df))
    notes.append(pairing_note(p.pairing))
    costs = measured_costs(p, locs[0], p.trail[start:], ranks, pairs, props)
    return pairs, Measured(locs[0], ranks, fusion, notes, costs)


def pairing_note(pairing: dict[str, Any]) -> str:
    """What pairs without poses mean for the tables, in words (method §13.2)."""
    by = pairing["by"]
    note = (
        f"Pairs by {by} (method §13.2): each query frame's reference is "
        f"{PAIRING_MODES[by].says}, and its place that frame and {pairing['place_frames']} "
        "neighbours each side"
    )
    note += (
        ", so R@N measures the localizer against its own choice (optimistic)."
        if kind_of(by) == "retrieval"
        else "."
    )
    agree = pairing.get("agreement_with_pose_pairs")
    if agree and agree["compared"]:
        note += (
            f" Where poses exist, {agree['agree']} of {agree['compared']} {by} pairs "
            f"({100 * agree['share']:.0f}%, 95% interval {100 * agree['share_ci_low']:.0f}-"
            f"{100 * agree['share_ci_high']:.0f}%) lie within {agree['within_m']:g} m of the pose "
            f"pair; a map frame drawn at random would in {100 * agree['chance_share']:.0f}%."
        )
    return note


def until_ranks(
    p: Context, check: bool = True
) -> tuple[dict[str, Entry], Table, Table, Table, list[Measured]]:
    """Every stage up to the ranks of every localizer (computed, or imported).

    With ``check``, inputs that can only give NaN tables are refused before any proposal work.
    Proposals are computed once and shared by the localizers that use the same method.

    Returns:
        (ingest entries, frames, annotations, pairs, one :class:`Measured` per localizer).
    """
    if kind_of(p.cfg.pairs.by) == "retrieval":
        ingested, frames, ann = until_annotations(p)
        pairs, m = pairs_by_retrieval(p, ingested, frames, ann, check)
        return ingested, frames, ann, pairs, [m]
    ingested, frames, ann, pairs = until_pairs(p)
    if check:
        check_inputs(p, ann, pairs)
    props = session_proposals(p, frames, pairs, ingested)
    measured = []
    for loc in p.localizer_list:
        start = len(p.trail)
        ranks = localizer_ranks(p, loc, frames, pairs, props)
        if not len(ranks.df):
            raise RetrievalError(f"localizer {loc.name}: no query subimage got a rank")
        fusion, notes = localizer_fusion(p, loc, ranks, len(pairs.df))
        if p.pairing:
            notes.append(pairing_note(p.pairing))
        costs = measured_costs(p, loc, p.trail[start:], ranks, pairs, props, frames)
        also = p.cfg.report.gt_radius_also
        ranks_also = ranks_at_radius(p, also, loc, frames, pairs, props) if also > 0 else None
        measured.append(Measured(loc, ranks, fusion, notes, costs, ranks_also))
    return ingested, frames, ann, pairs, measured


def run_all(p: Context) -> dict[str, Any]:
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
            Block(
                m.loc.name,
                samples.df,
                m.ranks.df,
                ordered_methods(m.fusion.methods),
                notes,
                m.costs,
                m.ranks_also.df if m.ranks_also is not None else None,
            )
        )
        keys_[m.loc.name] = {"ranks": m.ranks.key, "samples": samples.key}
        n_samples += len(samples.df)
    if len(measured) > 1:
        ranks_all = across_localizers(measured)
        fc = dataclasses.replace(
            p.cfg.fusion,
            methods=tuple(x for x in p.cfg.fusion.methods if x in rules_where(across=True)),
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
    outcome = RunOutcome(keys_, n_samples, reports, time.perf_counter() - t0)
    record = run_record(p, (ingested, frames, ann, pairs, measured), outcome)
    write_json(p.out / "run.json", record)
    if p.cfg.report.html:
        t_html = time.perf_counter()
        record["report_html"] = str(write_html_report(p.out))
        p.timings["report_html"] = time.perf_counter() - t_html
    record["table"] = reports.tables["I"]
    record["reports"] = reports
    return record


def check_localizer_set(p: Context) -> None:
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


def check_inputs(p: Context, ann: Table, pairs: Table) -> None:
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


# ---------------------------------------------------------------- helpers


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

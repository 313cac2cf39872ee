"""The stages as the chain calls them: each stage function with its sections of the run's config.

A stage function lives in its package (``harness/<stage>/stage.py``) and takes the run, its own
config sections and the tables before it; here each is handed what the root config and the run
say (method §3-10), and what a run records of it (frames not described, timings).
"""

from __future__ import annotations

import dataclasses
import time
from functools import partial

import pandas as pd

from harness.fusion import stage as fusion_stage
from harness.fusion.config import FusionConfig
from harness.ingest import stage as ingest_stage
from harness.pairs import stage as pair_stage
from harness.pipeline.context import Context
from harness.proposals import stage as proposal_stage
from harness.reports.blocks import Block, Reports
from harness.reports.write import write_reports
from harness.retrieval import described_frames
from harness.runtime.progress import progress
from harness.runtime.stage import Entry, RankTable, Table


def ingest_logs(p: Context) -> dict[str, Entry]:
    """Logs -> one ingest entry per session (:func:`harness.ingest.stage.ingest_logs`)."""
    return ingest_stage.ingest_logs(p, p.cfg.sessions, p.cfg.ingest, p.cfg.data_root)


def frame_table(p: Context, ingested: dict[str, Entry]) -> Table:
    """Ingest entries -> the run's frame table (:func:`harness.ingest.stage.frame_table`)."""
    return ingest_stage.frame_table(p, ingested, p.cfg.sessions, p.cfg.data_root)


def annotation_table(p: Context, frames: Table) -> Table:
    """The annotations, checked against the frames (:func:`harness.ingest.stage.annotation_table`).

    A learned descriptor's training sessions are not checked; ``harness detect`` reads only its
    sessions' rows, and none is fine.
    """
    skip = p.train_sessions or ()
    cfg = p.cfg
    return ingest_stage.annotation_table(
        frames, cfg.sessions, cfg.annotations, cfg.masks, skip, p.annotations_optional
    )


def query_pairs(p: Context, frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> the pairs (:func:`harness.pairs.stage.query_pairs`)."""
    cfg = p.cfg
    return pair_stage.query_pairs(p, cfg.pairs, cfg.sessions, cfg.seasons(), frames, ann)


def candidate_table(p: Context, frames: Table, ann: Table) -> Table:
    """Frames (+ annotations) -> pairing by retrieval's candidates (method §13.2)."""
    return pair_stage.candidate_table(p.cfg.pairs, p.cfg.seasons(), frames, ann)


def retrieval_pair_table(
    p: Context, frames: Table, cand: Table, described: dict[str, Entry], proposer: str
) -> Table:
    """Candidates + descriptors -> each query frame's map frame by retrieval (method §13.2)."""
    mb = p.cfg.retrieval.memory_mb
    return pair_stage.retrieval_pair_table(p, p.cfg.pairs, mb, frames, cand, described, proposer)


def session_proposals(
    p: Context,
    frames: Table,
    pairs: Table,
    ingested: dict[str, Entry],
    references: bool = True,
    methods: tuple[str, ...] | None = None,
) -> dict[str, Table]:
    """Frames + pairs -> each session's proposal boxes (method §5).

    Only on the frames ranking reads: a session's query frames and, for a reference session, the
    frames its database keeps (every frame unless ``[retrieval] db_stride_m``; none where
    ``references`` is False: every localizer ranks inside the paired frame); the others are
    counted in ``run.json`` (``counts.frames_not_described``), never proposed or encoded.
    ``methods``: only these of ``[proposals] methods`` (None: all).
    """
    stride = p.cfg.retrieval.db_stride_m
    described = described_frames(frames.df, pairs.df, stride, references)
    empty = frames.df.iloc[:0]
    mine = {sc.name: described.get(sc.name, empty) for sc in p.cfg.sessions}
    for name, fr in mine.items():
        p.not_described[name] = int((frames.df["session"] == name).sum()) - len(fr)
    pc = p.cfg.proposals
    if methods is not None:
        pc = dataclasses.replace(pc, methods=tuple(m for m in pc.methods if m in methods))
    return proposal_stage.session_proposals(p, pc, list(mine), mine, ingested)


def frame_proposals(
    p: Context, session: str, ingested: dict[str, Entry], rows: pd.DataFrame
) -> Table:
    """The proposal boxes of ``rows`` alone (frames of ``session``; method §5).

    For frames that a later step reads and the ranking did not: the no-change null's queries,
    where every localizer ranks inside the paired frame (no map frame was proposed for them).
    """
    pc = p.cfg.proposals
    return proposal_stage.session_proposals(p, pc, [session], {session: rows}, ingested)[session]


def fused_samples(
    p: Context, ranks: RankTable, frames: Table, ann: Table, fusion: FusionConfig | None = None
) -> Table:
    """Ranks + annotations -> samples (:func:`harness.fusion.stage.fused_samples`).

    ``fusion``: a localizer's own ``[fusion]`` (the run's when None).
    """
    fc = fusion or p.cfg.fusion
    return fusion_stage.fused_samples(p, fc, p.cfg.splits, ranks, frames, ann)


def change_tables(p: Context, blocks: list[Block], frames: Table, ann: Table) -> Reports:
    """Samples -> Tables I, S, P (and L), localization quality, splits and figures (method §8-11).

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

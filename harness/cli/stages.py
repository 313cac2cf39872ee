"""Handlers of the one-stage commands: fixture, ingest, pairs, proposals, rank, task."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from harness.cli.common import pipeline_of, run_config
from harness.errors import HarnessError


def cmd_fixture(args: argparse.Namespace) -> int:
    """``harness fixture``: generate the synthetic fixture world."""
    from harness.fixture import FixtureSpec, generate
    from harness.fixture.config import check_fixture

    spec = FixtureSpec.chosen(args)
    check_fixture(
        spec,
        "harness fixture",
        {k: "--" + k.replace("_", "-") for k in dataclasses.asdict(spec)},
    )
    formats = args.formats.split(",") if args.formats else None
    try:
        out = generate(
            Path(args.out), spec, all_formats=args.all_formats, formats=formats, force=args.force
        )
    except ValueError as err:
        raise HarnessError(f"harness fixture: {err}") from None
    print(f"fixture written to {out} (annotations: {out / 'annotations.csv'})")
    return 0


def cmd_ingest(args: argparse.Namespace) -> int:
    """``harness ingest``: one log into a frame table and an ingest report."""
    from harness.ingest import ingest_session
    from harness.ingest.config import IngestConfig, SessionConfig, check_ingest, check_session_name
    from harness.runtime.outdirs import check_replaceable, claim_dir

    if args.config:
        cfg = run_config(args)
        sessions, ic = cfg.sessions, cfg.ingest
        ic = dataclasses.replace(
            ic,
            salvage=ic.salvage or args.salvage,
            verify_images=ic.verify_images or args.verify_images,
        )
        for sc in sessions:  # check every session's output before any work
            check_replaceable(Path(args.out) / sc.name, "ingest", args.force)
        out = claim_dir(Path(args.out), "ingest-set")
        for sc in sessions:
            rep = ingest_session(sc, ic, out / sc.name, force=args.force)
            print(
                f"{sc.name}: {rep['frames_written']} frames -> {out / sc.name / 'frames.parquet'}"
            )
        return 0
    if not args.source or not args.session:
        raise HarnessError("ingest needs SOURCE and --session NAME, or --config FILE")
    check_session_name(args.session, "--session")
    check_session_name(args.camera, "--camera")
    sc = SessionConfig(
        name=args.session,
        source=str(Path(args.source).resolve()),
        camera=args.camera,
        image_topic=args.image_topic,
        pose_topic=args.pose_topic,
        tf_child_frame=args.tf_child_frame,
        fixed_frame=args.fixed_frame,
        camera_frame=args.camera_frame,
    )
    ic = IngestConfig(
        max_pose_gap_s=args.max_pose_gap,
        max_tf_gap_s=args.max_tf_gap,
        time_source=args.time_source,
        salvage=args.salvage,
        verify_images=args.verify_images,
    )
    check_ingest(
        ic,
        "harness ingest",
        {"max_pose_gap_s": "--max-pose-gap", "max_tf_gap_s": "--max-tf-gap"},
    )
    rep = ingest_session(sc, ic, Path(args.out), force=args.force)
    print(
        f"{rep['frames_written']} frames -> {Path(args.out) / 'frames.parquet'}; report: "
        f"{Path(args.out) / 'ingest_report.json'}"
    )
    print(f"dropped: {rep['dropped']}")
    return 0


def cmd_pairs(args: argparse.Namespace) -> int:
    """``harness pairs``: run up to the pairs and say where they are."""
    from harness.pipeline.chain import until_pairs

    p = pipeline_of(args)
    with p.locked():
        *_, pairs = until_pairs(p)
    d = p.cache.path("pairs", pairs.key)
    print(f"{len(pairs.df)} pairs -> {d / 'pairs.parquet'}\n{(d / 'summary.json').read_text()}")
    return 0


def cmd_proposals(args: argparse.Namespace) -> int:
    """``harness proposals``: run up to the proposals and say where they are."""
    from harness.pipeline.chain import until_pairs
    from harness.pipeline.stages import session_proposals

    p = pipeline_of(args)
    with p.locked():
        ing, frames, _, pairs = until_pairs(p)
        props = session_proposals(p, frames, pairs, ing)
    for s, t in props.items():
        print(
            f"{s}: {len(t.df)} proposals {t.df.groupby('proposal_method').size().to_dict()} -> "
            f"{p.cache.path('proposals', t.key) / 'proposals.parquet'}"
        )
    return 0


def cmd_rank(args: argparse.Namespace) -> int:
    """``harness rank``: run (or import) the ranks into ``ranks.parquet``."""
    from harness.pipeline.chain import check_localizer_set, until_ranks
    from harness.runtime.cache import write_json, write_parquet

    p = pipeline_of(args)
    with p.locked():
        check_localizer_set(p)
        *_, measured = until_ranks(p, check=False)
        import pandas as pd

        df = pd.concat(
            [m.ranks.df.assign(localizer=m.loc.name) for m in measured], ignore_index=True
        )
        counts = (
            measured[0].ranks.counts
            if len(measured) == 1
            else {m.loc.name: m.ranks.counts for m in measured}
        )
        write_parquet(p.out / "ranks.parquet", df)
        write_json(p.out / "rank_report.json", counts)
    print(f"{len(df)} ranked query subimages -> {p.out / 'ranks.parquet'}; counts: {counts}")
    return 0


def cmd_task(args: argparse.Namespace) -> int:
    """``harness task export``: the localization task for a user's localizer (method §12)."""
    from harness.localizers.task_export import write_task
    from harness.pipeline.chain import check_inputs, until_pairs
    from harness.pipeline.stages import session_proposals

    p = pipeline_of(args)
    with p.locked():
        ing, frames, ann, pairs = until_pairs(p)
        check_inputs(p, ann, pairs)
        props = session_proposals(p, frames, pairs, ing)
        keys = {
            "pairs": pairs.key,
            "proposals": {s: t.key for s, t in props.items()},
            "config": p.cfg.name,
        }
        counts = write_task(
            p.out / "task",
            frames.df,
            pairs.df,
            {s: t.df for s, t in props.items()},
            keys,
            args.images,
        )
    t = p.out / "task"
    print(
        f"task: {counts['query_subimages']} query subimages ({counts['query_images']} query "
        f"images) and {counts['reference_subimages']} reference subimages -> "
        f"{t / 'queries.csv'}, {t / 'references.csv'}, {t / 'databases.csv'}; what to write "
        f"back: {t / 'schema.md'}; then: harness reproduce --config {args.config} --out "
        f"{args.out} --import NAME=FILE"
    )
    return 0

"""Handlers of the whole-run commands: reproduce, report, detect."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from harness.cli.common import (
    DETECT_FLAGS,
    check_executor_flags,
    check_plugins_local,
    overrides_of,
    pipeline_of,
)
from harness.cli.console import print_block, print_localization, print_table_l
from harness.config.assemble import Overrides, folders_config
from harness.config.assemble import run_config as config_with
from harness.errors import HarnessError
from harness.reports.alarm_words import alarm_words


def cmd_reproduce(args: argparse.Namespace) -> int:
    """``harness reproduce``: the whole pipeline; prints Table I and where the reports are."""
    from rich.console import Console

    from harness.reports import tables as report_tables

    rec = pipeline_of(args).run()
    console = Console(width=max(Console().width, 140))
    reports = rec["reports"]
    blocks = reports.blocks or [reports]
    for rep in blocks:
        if len(rep.localization):
            print_localization(console, rep, rec)
        if rep.localization_also is not None and len(rep.localization_also):
            print_localization(console, rep, rec, also=True)
    if reports.table_l is not None:
        print_table_l(console, reports.table_l)
    for rep in blocks:
        print_block(console, rep, rec)
    extra = report_tables.written(Path(args.out))  # registered tables (harness/reports/tables.py)
    for spec, frame in extra:
        console.print(report_tables.to_console(spec, frame))
    print(
        f"reports in {Path(args.out)}: localization.md, "
        + ("tableL.md, " if reports.table_l is not None else "")
        + "".join(f"{spec.stem}.md, " for spec, _ in extra)
        + "table1.md, tableS.md, tableP.md, comparisons.md (+ .csv, .tex), "
        f"ranks.parquet, splits/, plots/, locmaps/, run.json ({rec['total_s']:.1f} s)"
    )
    if rec.get("report_html"):
        print(f"report: {rec['report_html']}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """``harness report``: (re)write ``report.html`` of an earlier run."""
    from harness.reports.html.page import write_html_report
    from harness.runtime.outdirs import claim_dir, read_run_record, run_lock

    if args.gallery is not None and args.gallery < 0:
        raise HarnessError(f"--gallery {args.gallery}: must be >= 0")
    out = Path(args.out)
    read_run_record(out)  # a finished run, its record readable
    out = claim_dir(out, "run")  # a run directory the harness wrote, nothing else
    with run_lock(out):
        path = write_html_report(out, args.gallery)
    print(f"report: {path}")
    return 0


def detect_overrides(args: argparse.Namespace) -> Overrides:
    """What ``harness detect``'s command line sets over its config.

    ``--preset``, each ``[detect]`` flag as typed, ``--annotations``, ``--masks``,
    ``--data-root``, ``--seed``.
    """
    typed = {k: getattr(args, k, None) for k in DETECT_FLAGS}
    return dataclasses.replace(
        overrides_of(args),
        annotations=Path(args.annotations) if args.annotations else None,
        masks=Path(args.masks) if args.masks else None,
        preset=getattr(args, "preset", None),
        detect={k: v for k, v in typed.items() if v is not None},
    )


def detect_sessions(args: argparse.Namespace) -> tuple[Any, str, list[str]]:
    """The assembled config, map and query sessions of ``harness detect``.

    Named in ``--config``, or two (or more) folders of images (``--map-images``,
    ``--query-images``; ``--config`` then gives the settings alone).
    """
    ov = detect_overrides(args)
    if args.map_images is not None or args.query_images:
        if args.map_images is None or not args.query_images:
            raise HarnessError("--map-images DIR and --query-images DIR go together")
        if args.map is not None or args.query:
            raise HarnessError("--map/--query name config sessions; with image folders, omit them")
        settings = Path(args.config) if args.config else None
        return folders_config(
            Path(args.map_images), list(args.query_images), settings, ov, "harness detect"
        )
    if args.config is None or args.map is None or not args.query:
        raise HarnessError(
            "detect needs --config with --map and --query, or --map-images DIR and "
            "--query-images DIR"
        )
    return config_with(Path(args.config), ov, command="harness detect"), args.map, list(args.query)


def _print_most_changed(frames: Any, top: int, null: bool = False) -> None:
    """The ``top`` most changed of a detect run's ``frames``, by file name where there are names.

    Uncertain pairs and pairs that are not comparable are left out (method §13.2, 13.5).
    ``null``: the scores are calibrated against the no-change null (else within the run), which
    the words name.
    """
    from harness.reports.alarm_words import in_words

    fr = frames.sort_values("score", ascending=False)
    if "uncertain_pair" in fr.columns:
        fr = fr[~fr["uncertain_pair"]]
    if "comparable" in fr.columns:  # a pair that could not be registered is never listed
        fr = fr[fr["comparable"].astype(bool)]
    fr = fr.head(top)
    named = "name" in fr.columns
    print(
        f"most changed frames ({'file name' if named else 'session camera utime'}: how often a "
        "frame with no change scores as high, the raw change score (no unit), the top box):"
    )
    for r in fr.itertuples():
        words = in_words(r.exceedance, "no-change null frames" if null else "frames of this run")
        label = r.name if named and r.name else f"{r.session} {r.camera} {r.utime}"
        print(
            f"  {label}: {words} (change score {r.score:.4g}), top box "
            f"[{r.top_x1:.0f}, {r.top_y1:.0f}, {r.top_x2:.0f}, {r.top_y2:.0f}]"
        )


def cmd_detect(args: argparse.Namespace) -> int:
    """``harness detect``: change boxes, scores and maps of new sessions (method §13)."""
    from harness.apps.warm import start_detect_workers

    check_executor_flags(args)
    cfg, map_session, queries = detect_sessions(args)
    check_plugins_local(args)
    start_detect_workers(cfg)  # they load their modules while the detector's load
    from harness.apps.detect import run_detect
    from harness.pairs.modes import PAIRING_MODES
    from harness.runtime.executors import make_executor

    result = run_detect(
        cfg,
        map_session,
        queries,
        Path(args.out),
        executor=make_executor(args.executor, args.address, args.ray_cpus),
        rerun=Path(args.rerun) if args.rerun else None,
    )
    out, rec = Path(args.out), result.record
    names = rec.get("folders") or [rec["map"], *rec["queries"]]  # a folder run: its folders
    print(
        f"detect: {rec['query_frames']} query frames of {', '.join(names[1:])} against the "
        f"map {names[0]}, {rec['detections']} change boxes, {rec['ms_per_query_frame']:.1f} "
        f"ms per query frame ({rec['total_s']:.1f} s)"
    )
    null = rec.get("calibration", {}).get("method") == "null"
    _print_most_changed(result.frames, cfg.detect.top, null)
    print(
        alarm_words(rec["alarm"], rec.get("calibration", {}))
    )  # docs/decisions.md, *Calibrated alarms*
    agree = rec.get("pairing", {}).get("agreement_with_pose_pairs")
    if rec.get("pairing"):
        by = rec["pairing"]["by"]
        print(
            f"pairs by {by} (method §13.2): each query frame's reference is "
            f"{PAIRING_MODES[by].says}"
            + (
                f"; {agree['agree']} of {agree['compared']} ({100 * agree['share']:.0f}%, 95% "
                f"interval {100 * agree['share_ci_low']:.0f}-{100 * agree['share_ci_high']:.0f}%) "
                f"within {agree['within_m']:g} m of the pose pair (a random map frame: "
                f"{100 * agree['chance_share']:.0f}%)"
                if agree and agree["compared"]
                else " (no poses to compare with)"
            )
        )
    if rec.get("uncertain_pairs"):
        print(
            f"uncertain pairs: {rec['uncertain_pairs']} of {rec['query_frames']} query frames "
            f"have a pair_confidence under {rec['min_pair_confidence']:g} ([pairs] "
            "min_pair_confidence): flagged in frames.csv (uncertain_pair), left out of the most "
            "changed frames, marked on the page"
        )
    if rec.get("thin_boxes_dropped"):
        print(
            f"dropped {rec['thin_boxes_dropped']} candidate boxes under "
            f"{rec['options']['min_box_side']:g} px a side ([detect] min_box_side)"
        )
    if result.table_d_markdown:
        print(result.table_d_markdown)
    if result.pixel_markdown:
        print(result.pixel_markdown)
    print(
        f"outputs in {out}: detections.json + images.json (COCO), frames.parquet/.csv, "
        f"locmaps/, trajectory.png, detect.html"
    )
    if rec.get("rerun"):
        rr_ = rec["rerun"]
        print(
            f"rerun recording: {rr_['path']} ({rr_['query_frames']} query frames, "
            f"{rr_['change_boxes']} change boxes; open it with: rerun {rr_['path']})"
        )
    return 0

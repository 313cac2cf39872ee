"""The argument parser: every subcommand, its flags and its handler."""

from __future__ import annotations

import argparse
from typing import Any

from harness.cli.common import detect_flag
from harness.cli.runs import cmd_detect, cmd_report, cmd_reproduce
from harness.cli.stages import cmd_fixture, cmd_ingest, cmd_pairs, cmd_proposals, cmd_rank, cmd_task
from harness.cli.tools import cmd_annotations, cmd_gc, cmd_inspect
from harness.detect.config import BOX_GENERATORS, BOX_PRIORS, BOX_SCORES, CALIBRATIONS
from harness.detect.presets import PRESETS, preset_help
from harness.methods import rules_where


def build_parser() -> argparse.ArgumentParser:
    """The ``harness`` argument parser: one subcommand per stage."""
    ap = argparse.ArgumentParser(
        prog="harness", description="Detection-by-Localization benchmark harness"
    )
    ap.add_argument("-v", "--verbose", action="store_true")
    ap.add_argument(
        "--plugin",
        action="append",
        default=[],
        metavar="FILE.py",
        help="a Python file of yours that registers methods (a fusion rule, a proposer, a "
        "localizer kind, a log format); repeatable; before the command",
    )
    sub = ap.add_subparsers(dest="cmd", required=True)

    _add_fixture(sub)
    _add_ingest(sub)
    _add_stage_commands(sub)
    _add_detect(sub)
    _add_task(sub)
    _add_report(sub)
    _add_gc(sub)
    _add_inspect(sub)
    _add_annotations(sub)
    return ap


def _add_fixture(sub: Any) -> None:
    """``harness fixture``."""
    p = sub.add_parser("fixture", help="generate the synthetic fixture world as real logs")
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=64, help="frames per session")
    p.add_argument("--width", type=int, default=120)
    p.add_argument("--height", type=int, default=160)
    p.add_argument("--objects", type=int, default=9, help="change objects per changed session")
    p.add_argument(
        "--loop-scale", type=float, default=1.5, help="size of the loop road (1.0: 60 m x 40 m)"
    )
    p.add_argument(
        "--render-scale",
        type=int,
        default=1,
        help="ray-cast at 1/scale resolution, then upsample (fast large frames)",
    )
    p.add_argument(
        "--formats",
        default=None,
        help="comma-separated log format per session (one name: all sessions), e.g. ros2",
    )
    p.add_argument(
        "--all-formats", action="store_true", help="write every session in every log format"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out if it is a fixture the harness generated",
    )
    p.set_defaults(func=cmd_fixture)


def _add_ingest(sub: Any) -> None:
    """``harness ingest``."""
    p = sub.add_parser("ingest", help="turn a season log into frames.parquet")
    p.add_argument("source", nargs="?")
    p.add_argument("--session")
    p.add_argument("--out", required=True)
    p.add_argument("--config")
    p.add_argument("--data-root")
    p.add_argument("--camera", default="Cam5")
    p.add_argument("--image-topic")
    p.add_argument("--pose-topic")
    p.add_argument("--tf-child-frame", help="older name of --camera-frame")
    p.add_argument(
        "--fixed-frame", help="/tf: the frame poses are expressed in (default: the tree's root)"
    )
    p.add_argument(
        "--camera-frame", help="/tf: the camera's frame (default: the images' header.frame_id)"
    )
    p.add_argument(
        "--max-tf-gap",
        type=float,
        default=1.0,
        help="seconds, for /tf transforms slower than --max-pose-gap",
    )
    p.add_argument("--time-source", choices=["header", "log"], default="header")
    p.add_argument("--max-pose-gap", type=float, default=0.1, help="seconds")
    p.add_argument(
        "--salvage", action="store_true", help="keep the frames read before a damaged part of a log"
    )
    p.add_argument(
        "--verify-images",
        action="store_true",
        help="decode every compressed image fully; drop and count broken ones",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out if it is an earlier ingest output of the harness",
    )
    p.set_defaults(func=cmd_ingest)


def _add_stage_commands(sub: Any) -> None:
    """``pairs``, ``proposals``, ``rank`` and ``reproduce``: a config and an output folder."""
    for name, func, hlp in (
        ("pairs", cmd_pairs, "build cross-season pairs"),
        ("proposals", cmd_proposals, "compute object proposals"),
        ("rank", cmd_rank, "ranks of the ground-truth reference per query subimage"),
        ("reproduce", cmd_reproduce, "run the whole pipeline and write Table I"),
    ):
        p = sub.add_parser(name, help=hlp)
        p.add_argument("--config", required=True)
        p.add_argument("--out", required=True)
        p.add_argument("--data-root", help="replaces {data_root} and data_root in the config")
        if name == "reproduce":  # the stages before the tables draw nothing from the run's seed
            p.add_argument(
                "--seed",
                type=int,
                help="the run's seed (config `seed`): bootstrap resamples and chance draws",
            )
        p.add_argument(
            "--executor",
            choices=["local", "ray"],
            default="local",
            help="where stage units run (ray: pip install 'dbl-harness[ray]')",
        )
        p.add_argument("--address", help="Ray cluster address (default: start a local cluster)")
        p.add_argument("--ray-cpus", type=int, help="workers of a local Ray cluster")
        if name in ("rank", "reproduce"):
            p.add_argument(
                "--import",
                dest="rank_import",
                metavar="NAME=FILE",
                help="ranked lists of your own localizer, named NAME (a bare FILE: its stem); "
                "the task to rank: harness task export",
            )
            p.add_argument(
                "--force",
                action="store_true",
                help="replace the tables of a run directory that measured another localizer",
            )
        p.set_defaults(func=func)


def _add_folders(p: Any) -> None:
    """``harness detect``'s image folders and their annotations (method §13.2)."""
    p.add_argument(
        "--map-images",
        metavar="DIR",
        help="a folder of map images, no poses needed (method §13.2): the session 'map'",
    )
    p.add_argument(
        "--query-images",
        metavar="DIR",
        action="append",
        help="a folder of new images (repeat for several): sessions 'query', 'query2', ...",
    )
    p.add_argument(
        "--annotations",
        metavar="FILE",
        help="annotations of the new frames (replaces the config's): by session, camera, utime, "
        "or by image file name (an image column) for image folders",
    )
    p.add_argument(
        "--masks",
        metavar="DIR",
        help="change masks as annotations (replaces [masks] folder): one 0/255 image per "
        "annotated image, named like it",
    )


def _add_alarms(p: argparse.ArgumentParser) -> None:
    """``harness detect``'s alarms: the nominal rate and what the scores are calibrated against."""
    detect_flag(
        p,
        "--alarm",
        type=float,
        metavar="RATE",
        help="the nominal false-alarm rate: boxes and frames whose calibrated score is at most "
        "it go to alarms.csv",
    )
    detect_flag(
        p,
        "--calibration",
        choices=CALIBRATIONS,
        help="what the calibrated scores are measured against: null (pairs of map frames that "
        "hold no change by construction, [detect.null]) or within-run (the run's own frames "
        "and boxes)",
    )


def _add_detect(sub: Any) -> None:
    """``harness detect``."""
    p = sub.add_parser(
        "detect", help="what changed: the detector on new sessions against a map session"
    )
    p.add_argument(
        "--config",
        help="sessions, localizer(s); annotations optional (with --map-images: the settings alone)",
    )
    p.add_argument("--map", help="the map (reference) session of the config")
    p.add_argument("--query", action="append", help="a new session (repeat for several)")
    _add_folders(p)
    p.add_argument("--out", required=True)
    p.add_argument("--data-root", help="replaces {data_root} and data_root in the config")
    detect_flag(
        p,
        "--fusion",
        "--method",  # its name before the one vocabulary
        dest="fusion",
        default=None,
        help="the fusion rule whose LoC finds the boxes (--method: its old name): "
        f"{', '.join(rules_where(detect=True))} (the field's rules: method §14), or a method "
        "registered with detect=True",
    )
    detect_flag(p, "--boxes", help=f"the box generator (method §13.1): {', '.join(BOX_GENERATORS)}")
    p.add_argument(
        "--preset",
        choices=tuple(PRESETS),
        help="a whole detector by name (its flags below win over it): " + preset_help(),
    )
    detect_flag(
        p,
        "--localizer",
        metavar="KIND",
        help="what ranks the subimages: keypoints (each box's share of keypoints that do not "
        "localize in its paired map frame), local (each box ranked inside its paired map frame by "
        "NCC, method §13.3), another localizer kind that ranks inside the paired frame (a "
        "plugin's), or config (the config's localizers)",
    )
    detect_flag(
        p,
        "--proposals",
        metavar="METHOD",
        help="the proposal method whose boxes the local or keypoints localizer ranks: selective "
        "(Selective Search) or segments (the frame's colour regions)",
    )
    detect_flag(
        p,
        "--box-prior",
        choices=BOX_PRIORS,
        help="what a box's score is fused with: difference_product (the registered pair's plain "
        "difference times the score to the power [detect] localization_weight), difference "
        "(their within-frame percentiles), area (its percentile by area in its frame, method "
        "§13.3) or none (the score alone, the paper's detector)",
    )
    detect_flag(
        p,
        "--box-score",
        help=f"how a generator other than fused scores a box from the LoC map: "
        f"{', '.join(BOX_SCORES)}",
    )
    _add_alarms(p)
    detect_flag(p, "--nms-iou", type=float, help="the boxes' NMS IoU")
    detect_flag(p, "--max-boxes", type=int, help="change boxes per frame at most")
    detect_flag(p, "--top", type=int, help="most changed places shown")
    p.add_argument(
        "--rerun",
        metavar="OUT.rrd",
        help="also write a recording for the Rerun viewer (needs dbl-harness[rerun])",
    )
    p.add_argument("--executor", choices=["local", "ray"], default="local")
    p.add_argument("--address", help="Ray cluster address (default: start a local cluster)")
    p.add_argument("--ray-cpus", type=int, help="workers of a local Ray cluster")
    p.set_defaults(func=cmd_detect)


def _add_task(sub: Any) -> None:
    """``harness task``."""
    p = sub.add_parser("task", help="the localization task for your own localizer")
    tsub = p.add_subparsers(dest="action", required=True)
    p = tsub.add_parser(
        "export",
        help="write OUT/task/: query subimages, reference frames with boxes, upright images, "
        "the import schema (nothing is trained)",
    )
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, help="the run directory a later reproduce uses")
    p.add_argument("--data-root", help="replaces {data_root} and data_root in the config")
    p.add_argument(
        "--images",
        choices=["upright", "source"],
        default="upright",
        help="upright: write rotated frames upright as PNG (default); source: name the stored "
        "files with a rotation column",
    )
    p.set_defaults(func=cmd_task, executor="local", address=None, ray_cpus=None)


def _add_report(sub: Any) -> None:
    """``harness report``."""
    p = sub.add_parser("report", help="(re)write OUT/report.html for an existing run")
    p.add_argument("out", help="a run directory (the --out of harness reproduce)")
    p.add_argument(
        "--gallery",
        type=int,
        help="thumbnails per method and kind (default: the run's [report] gallery)",
    )
    p.set_defaults(func=cmd_report)


def _add_gc(sub: Any) -> None:
    """``harness gc``."""
    p = sub.add_parser("gc", help="remove the cache entries of OUT that its last run did not use")
    p.add_argument("out", help="a run directory (the --out of harness reproduce)")
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="list what would be removed, and its size; remove nothing",
    )
    p.set_defaults(func=cmd_gc)


def _add_inspect(sub: Any) -> None:
    """``harness inspect``."""
    p = sub.add_parser(
        "inspect",
        help="what is in a log: topics, rates, images, the tf tree, and config lines to ingest it",
    )
    p.add_argument("log", help="an NCLT root, a .bag, a ROS2 bag directory or an .mcap")
    p.add_argument("--json", action="store_true", help="print the description as JSON")
    p.set_defaults(func=cmd_inspect)


def _add_annotations(sub: Any) -> None:
    """``harness annotations``."""
    p = sub.add_parser(
        "annotations", help="import annotations from labelling tools, or export a labelling task"
    )
    asub = p.add_subparsers(dest="action", required=True)
    pi = asub.add_parser("import")
    pi.add_argument("format", choices=["coco", "voc", "cvat"])
    pi.add_argument("src")
    pi.add_argument("--out", required=True)
    pi.add_argument("--frames", help="frames.parquet to validate against")
    pi.add_argument("--force", action="store_true", help="replace --out if it exists")
    pi.set_defaults(func=cmd_annotations)
    pe = asub.add_parser("export")
    pe.add_argument("--pairs", required=True)
    pe.add_argument("--frames", required=True)
    pe.add_argument("--out", required=True)
    pe.add_argument("--limit", type=int)
    pe.add_argument(
        "--force",
        action="store_true",
        help="replace --out if it is a labelling task the harness wrote",
    )
    pe.set_defaults(func=cmd_annotations)

"""Handlers of the tools: annotations, inspect, gc."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from harness.errors import HarnessError
from harness.records import IMAGE_KEY

log = logging.getLogger("harness")


def cmd_annotations(args: argparse.Namespace) -> int:
    """``harness annotations``: export frames for labelling or import a labelled set."""
    from harness.ingest.label_formats import export_for_labelling, import_annotations

    if args.action == "import":
        frames = None
        if args.frames:
            from harness.ingest import load_frames

            frames = load_frames(Path(args.frames))
        df = import_annotations(
            args.format, Path(args.src), frames, Path(args.out), force=args.force
        )
        print(f"{len(df)} annotation rows -> {args.out}")
        return 0
    import pandas as pd

    from harness.ingest import load_frames
    from harness.inputs import check_input
    from harness.runtime.outdirs import check_replaceable

    check_replaceable(Path(args.out), "labelling-task", args.force)  # before reading anything
    pairs_path = check_input(args.pairs, "pair table", HarnessError)
    try:
        pairs = pd.read_parquet(pairs_path)
    except (OSError, ValueError) as err:
        raise HarnessError(f"{pairs_path}: not a readable parquet pair table ({err})") from None
    need = [*IMAGE_KEY, "r_camera", "r_utime"]
    if [c for c in need if c not in pairs.columns]:
        raise HarnessError(
            f"{pairs_path}: not a pair table (needs columns {need}; the run's is "
            "OUT/cache/pairs/<key>/pairs.parquet)"
        )

    if args.limit is not None and args.limit < 1:
        raise HarnessError(f"--limit {args.limit}: must be >= 1")
    out = export_for_labelling(
        pairs, load_frames(Path(args.frames)), Path(args.out), args.limit, force=args.force
    )
    print(f"labelling task written to {out} (task.json + images/)")
    return 0


def _print_folder(console: Any, info: dict[str, Any]) -> None:
    """``harness inspect DIR``'s table of a folder session and its config lines."""
    from rich.table import Table

    t = Table(title="Folder")
    t.add_column("")
    t.add_column("")
    sizes = ", ".join(f"{k} ({v})" for k, v in info["sizes"].items())
    first = "" if info["first_s"] is None else f"{info['first_s']:.3f}"
    for k, v in (
        ("images", str(info["images"])),
        ("sizes (width x height)", sizes),
        ("first / last", f"{info['first']} / {info['last']}"),
        ("file names", info["names"] + (" (times.txt used)" if info["times_file"] else "")),
        ("times increase in name order", "yes" if info["in_order"] else "NO"),
        (
            "span s / rate Hz / first s",
            f"{info['span_s']:.2f} / {info['rate_hz']:.2f} / {first}",
        ),
        ("poses", str(info["poses"]) if info["poses"] else "none (no trajectory)"),
    ):
        t.add_row(k, v)
    console.print(t)
    console.print("[bold]config lines[/]")
    console.print(info["suggested_config"], markup=False, highlight=False)


def cmd_inspect(args: argparse.Namespace) -> int:
    """``harness inspect``: topics, image encodings and the tf tree of a log."""
    import json

    from rich.console import Console
    from rich.table import Table

    from harness.ingest.inspect import inspect_log

    info = inspect_log(Path(args.log))
    if args.json:
        print(json.dumps(info, indent=2, default=str))
        return 0
    console = Console(width=max(Console().width, 140))
    console.print(f"[bold]{info['path']}[/] ({info['format']})")
    if "names" in info:  # a folder session
        _print_folder(console, info)
        return 0
    if "sessions" in info:  # a layout of sessions (nclt)
        t = Table(title="NCLT sessions")
        for c in ("session", "cameras (images)", "ground-truth rows"):
            t.add_column(c)
        for s in info["sessions"]:
            t.add_row(
                s["session"],
                ", ".join(f"{k} ({v})" for k, v in s["cameras"].items()),
                str(s["ground_truth_rows"]),
            )
        console.print(t)
    else:
        t = Table(title="Topics")
        for c, j in (
            ("topic", "left"),
            ("type", "left"),
            ("messages", "right"),
            ("rate Hz", "right"),
            ("span s", "right"),
            ("first s", "right"),
        ):
            t.add_column(c, justify=j)  # type: ignore[arg-type]
        for r in info["topics"]:
            t.add_row(
                r["topic"],
                r["type"],
                str(r["messages"]),
                f"{r['rate_hz']:.2f}",
                f"{r['span_s']:.2f}",
                "" if r["first_s"] is None else f"{r['first_s']:.3f}",
            )
        console.print(t)
        if info["images"]:
            t = Table(title="Images")
            for c in ("topic", "encoding", "size", "frame_id"):
                t.add_column(c)
            for topic, im in info["images"].items():
                t.add_row(topic, im["encoding"], f"{im['width']}x{im['height']}", im["frame_id"])
            console.print(t)
        if info["tf"]:
            t = Table(title=f"tf tree (roots: {', '.join(info['tf_roots'])})")
            for c in ("parent", "child", "kind", "transforms", "rate Hz"):
                t.add_column(c)
            for e in info["tf"]:
                t.add_row(
                    e["parent"],
                    e["child"],
                    "static" if e["static"] else "dynamic",
                    str(e["transforms"]),
                    f"{e['rate_hz']:.2f}",
                )
            console.print(t)
    console.print("Config lines that would ingest it:", style="bold")
    print(info["suggested_config"])
    return 0


def cmd_gc(args: argparse.Namespace) -> int:
    """``harness gc``: remove (or list, ``--dry-run``) cache entries the last run did not use."""
    from harness.runtime.gc import collect_garbage

    res = collect_garbage(Path(args.out), dry_run=args.dry_run)
    verb = "would remove" if args.dry_run else "removed"
    for entry in res.removed:
        print(f"  {verb}: cache/{entry}")
    for entry in res.foreign:
        print(f"  left alone (not written by the harness): {entry}")
    print(
        f"{verb} {len(res.removed)} cache entries ({res.bytes_removed / 1e6:.1f} MB) that "
        f"the last run did not use; kept {res.kept}"
    )
    return 0

"""``harness``: one subcommand per stage plus ``reproduce``.

Library errors become one ``ERROR:`` line and exit 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import logging
import sys
from pathlib import Path

from .errors import HarnessError

log = logging.getLogger("harness")


_FS_ERRORS = {
    errno.ENOSPC: "free disk space (completed stages are kept) and rerun the same command "
    "to resume",
    errno.EDQUOT: "free disk space within the quota and rerun the same command to resume",
    errno.EROFS: "the file system is read-only: choose a writable --out",
    errno.EACCES: "no permission: choose a writable --out or fix the permissions",
    errno.EPERM: "operation not permitted: choose another --out or fix the permissions",
}


def _setup_logging(verbose: bool) -> None:
    from rich.logging import RichHandler

    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(message)s",
        handlers=[RichHandler(show_path=False, rich_tracebacks=False, log_time_format="%H:%M:%S")],
        force=True,
    )


def _config(args: argparse.Namespace):
    from .config import load_config

    cfg = load_config(Path(args.config), getattr(args, "data_root", None))
    if getattr(args, "seed", None) is not None:
        cfg = dataclasses.replace(cfg, seed=args.seed)
    return cfg


def cmd_fixture(args: argparse.Namespace) -> int:
    """``harness fixture``: generate the synthetic fixture world."""
    from .fixture import FixtureSpec, generate

    spec = FixtureSpec(
        seed=args.seed,
        frames=args.frames,
        width=args.width,
        height=args.height,
        objects=args.objects,
        loop_scale=args.loop_scale,
        render_scale=args.render_scale,
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
    from .config import IngestConfig, SessionConfig, check_session_name
    from .ingest import ingest_session
    from .outdirs import check_replaceable, claim_dir

    if args.config:
        cfg = _config(args)
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
    if args.max_pose_gap <= 0:
        raise HarnessError(f"--max-pose-gap {args.max_pose_gap}: must be > 0 seconds")
    if args.max_tf_gap <= 0:
        raise HarnessError(f"--max-tf-gap {args.max_tf_gap}: must be > 0 seconds")
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
    rep = ingest_session(sc, ic, Path(args.out), force=args.force)
    print(
        f"{rep['frames_written']} frames -> {Path(args.out) / 'frames.parquet'}; report: "
        f"{Path(args.out) / 'ingest_report.json'}"
    )
    print(f"dropped: {rep['dropped']}")
    return 0


def _pipeline(args: argparse.Namespace):
    from .executors import make_executor
    from .runner import Pipeline

    if args.executor != "ray" and (args.address is not None or args.ray_cpus is not None):
        raise HarnessError("--address and --ray-cpus need --executor ray")
    if args.ray_cpus is not None and args.ray_cpus < 1:
        raise HarnessError(f"--ray-cpus {args.ray_cpus}: must be >= 1")
    cfg = _config(args)  # validated before any executor or directory is set up
    rank_import = None
    if getattr(args, "rank_import", None):
        from .retrieval.imported import parse_import_arg

        rank_import = parse_import_arg(args.rank_import)
        if not rank_import.path.is_file():
            raise HarnessError(
                f"{rank_import.path}: --import file not found (localizer {rank_import.name!r})"
            )
    return Pipeline(
        cfg,
        Path(args.out),
        rank_import=rank_import,
        force=bool(getattr(args, "force", False)),
        executor=make_executor(args.executor, args.address, args.ray_cpus),
    )


def cmd_pairs(args: argparse.Namespace) -> int:
    """``harness pairs``: run up to the pairs and say where they are."""
    from .runner import until_pairs

    p = _pipeline(args)
    with p.locked():
        *_, pairs = until_pairs(p)
    d = p.cache.path("pairs", pairs.key)
    print(f"{len(pairs.df)} pairs -> {d / 'pairs.parquet'}\n{(d / 'summary.json').read_text()}")
    return 0


def cmd_proposals(args: argparse.Namespace) -> int:
    """``harness proposals``: run up to the proposals and say where they are."""
    from .runner import session_proposals, until_pairs

    p = _pipeline(args)
    with p.locked():
        ing, frames, _, pairs = until_pairs(p)
        props = session_proposals(p, frames, pairs, ing)
    for s, t in props.items():
        print(
            f"{s}: {len(t.df)} proposals {t.df.groupby('method').size().to_dict()} -> "
            f"{p.cache.path('proposals', t.key) / 'proposals.parquet'}"
        )
    return 0


def cmd_rank(args: argparse.Namespace) -> int:
    """``harness rank``: run (or import) the ranks into ``ranks.parquet``."""
    from .cache import write_json, write_parquet
    from .runner import check_localizer_set, until_ranks

    p = _pipeline(args)
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


def cmd_detect(args: argparse.Namespace) -> int:
    """``harness detect``: change boxes, scores and maps of new sessions (SPEC 13)."""
    from .detect import DetectOptions, run_detect
    from .executors import make_executor

    if args.executor != "ray" and (args.address is not None or args.ray_cpus is not None):
        raise HarnessError("--address and --ray-cpus need --executor ray")
    cfg = _config(args)
    opt = DetectOptions(
        method=args.method,
        nms_iou=args.nms_iou,
        max_boxes=args.max_boxes,
        top=args.top,
        seed=cfg.fusion.seed,
    )
    rec = run_detect(
        cfg,
        args.map,
        list(args.query),
        Path(args.out),
        opt,
        make_executor(args.executor, args.address, args.ray_cpus),
    )
    out = Path(args.out)
    print(
        f"detect: {rec['query_frames']} query frames of {', '.join(rec['queries'])} against the "
        f"map {rec['map']}, {rec['detections']} change boxes, {rec['ms_per_query_frame']:.1f} "
        f"ms per query frame ({rec['total_s']:.1f} s)"
    )
    fr = pd_read(out / "frames.parquet").sort_values("score", ascending=False).head(args.top)
    print("most changed frames (session camera utime: score, top box):")
    for r in fr.itertuples():
        print(
            f"  {r.session} {r.camera} {r.utime}: {r.score:.4g}, "
            f"[{r.top_x1:.0f}, {r.top_y1:.0f}, {r.top_x2:.0f}, {r.top_y2:.0f}]"
        )
    if rec.get("table_d"):
        print((out / "tableD.md").read_text())
    print(
        f"outputs in {out}: detections.json + images.json (COCO), frames.parquet/.csv, "
        f"locmaps/, trajectory.png, detect.html"
    )
    return 0


def pd_read(path: Path):
    """A parquet table (pandas imported only when a command needs it)."""
    import pandas as pd

    return pd.read_parquet(path)


def cmd_task(args: argparse.Namespace) -> int:
    """``harness task export``: the localization task for a user's localizer (SPEC 12)."""
    from .runner import check_inputs, session_proposals, until_pairs
    from .task_export import write_task

    p = _pipeline(args)
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


def _print_change_table(console, rep, table: str, title: str) -> None:
    """One change table with intervals, the floor row, and its confound warnings."""
    from rich.table import Table

    from .methods import FUSION_METHODS, METHOD_LABELS
    from .reports import pivot

    ap, lo, hi = (pivot(rep.summary, table, rep.methods, v) for v in ("ap", "ci_low", "ci_high"))
    floor = pivot(rep.summary, table, rep.methods, "floor")
    t = Table(title=title)
    t.add_column("AP [95% CI]")
    for c in ap.columns:
        t.add_column(f"{c:.2f}" if isinstance(c, float) else str(c), justify="right")
    shown_sep = False
    for m in ap.index:
        if m not in FUSION_METHODS and not shown_sep:
            t.add_section()
            shown_sep = True
        t.add_row(
            METHOD_LABELS[m],
            *(
                "NaN"
                if ap.loc[m, c] != ap.loc[m, c]
                else f"{ap.loc[m, c]:.2f} [{lo.loc[m, c]:.2f}, {hi.loc[m, c]:.2f}]"
                if lo.loc[m, c] == lo.loc[m, c]
                else f"{ap.loc[m, c]:.2f}"
                for c in ap.columns
            ),
        )
    t.add_section()
    ref = next((m for m in ("rank_fusion", "score_max") if m in floor.index), floor.index[0])
    t.add_row(
        "floor (random ranking)",
        *(
            "NaN" if floor.loc[ref, c] != floor.loc[ref, c] else f"{floor.loc[ref, c]:.2f}"
            for c in ap.columns
        ),
    )
    console.print(t)
    for w in rep.warnings[table]:
        console.print(f"[bold yellow]{w}[/]")


def cmd_reproduce(args: argparse.Namespace) -> int:
    """``harness reproduce``: the whole pipeline; prints Table I and where the reports are."""
    from rich.console import Console

    rec = _pipeline(args).run()
    console = Console(width=max(Console().width, 140))
    reports = rec["reports"]
    blocks = reports.blocks or [reports]
    for rep in blocks:
        if len(rep.localization):
            _print_localization(console, rep, rec)
    if reports.table_l is not None:
        _print_table_l(console, reports.table_l)
    for rep in blocks:
        _print_block(console, rep, rec)
    print(
        f"reports in {Path(args.out)}: localization.md, "
        + ("tableL.md, " if reports.table_l is not None else "")
        + "table1.md, tableS.md, tableP.md, comparisons.md (+ .csv, .tex), "
        f"ranks.parquet, splits/, plots/, locmaps/, run.json ({rec['total_s']:.1f} s)"
    )
    if rec.get("report_html"):
        print(f"report: {rec['report_html']}")
    return 0


def _print_table_l(console, t) -> None:
    """Table L (SPEC section 11): a row per localizer and the fused row, then the floor."""
    from rich.table import Table

    from .leaderboard import AP_COLUMNS

    first = str(t["localizer"].iloc[0])
    lt = Table(title=f"Table L: localizers (Table S at RoC-max {t['roc_max'].iloc[0]:.2f})")
    for c in ("localizer", "R@1", "R@5", *(h for *_, h in AP_COLUMNS), f"S rank fusion - {first}"):
        lt.add_column(c, justify="left" if c == "localizer" else "right")

    def ap(r, pfx: str) -> str:
        v, lo, hi = (r[f"{pfx}_{k}"] for k in ("ap", "ci_low", "ci_high"))
        return "-" if v != v else (f"{v:.2f} [{lo:.2f}, {hi:.2f}]" if lo == lo else f"{v:.2f}")

    for _, r in t.iterrows():
        d = r["S_rank_fusion_diff"]
        lt.add_row(
            str(r["localizer"]),
            *("" if v != v else f"{v:.2f}" for v in (r["recall_at_1"], r["recall_at_5"])),
            *(ap(r, pfx) for pfx, *_ in AP_COLUMNS),
            ""
            if d != d
            else f"{d:+.2f} [{r['S_rank_fusion_diff_ci_low']:+.2f}, "
            f"{r['S_rank_fusion_diff_ci_high']:+.2f}]",
        )
    lt.add_section()
    r0 = t.iloc[0]
    lt.add_row(
        f"floor ({first})",
        "",
        "",
        *(f"{r0[f'{pfx}_floor']:.2f}" for pfx, *_ in AP_COLUMNS),
        "",
    )
    console.print(lt)


def _print_localization(console, rep, rec) -> None:
    """One localizer's localization quality (all season pairs)."""
    from rich.table import Table

    from .reports import LOC_COLUMNS

    loc = rep.localization
    lt = Table(
        title=f"Localization quality of {rep.localizer} (ground truth: place within "
        f"{rec['config']['retrieval']['gt_radius_m']:g} m)"
    )
    lt.add_column("props")
    lt.add_column("pair")
    for _, lab, _ in LOC_COLUMNS:
        lt.add_column(lab, justify="right")
    for r in loc[loc["season_pair"] == "all"].itertuples(index=False):
        lt.add_row(
            r.proposals,
            r.season_pair,
            *(
                str(int(getattr(r, c)))
                if d == 0
                else ("NaN" if getattr(r, c) != getattr(r, c) else f"{getattr(r, c):.{d}f}")
                for c, _, d in LOC_COLUMNS
            ),
        )
    console.print(lt)
    print("  per season pair: localization.md")


def _print_block(console, rep, rec) -> None:
    """One block's Tables I, S and P and its paired comparisons (Table S, last RoC-max)."""
    name = f"{rec['config']['name']}, localizer {rep.localizer}"
    _print_change_table(console, rep, "I", f"Table I: AP by RoC-max, the paper's protocol ({name})")
    _print_change_table(console, rep, "S", f"Table S: size-stratified AP by RoC-max ({name})")
    _print_change_table(console, rep, "P", f"Table P: pixel AP and image AP ({name})")
    summ = rep.summary
    cmp_ = summ[
        (summ["table"] == "S")
        & (summ["proposals"] == "all")
        & (summ["season_pair"] == "all")
        & summ["diff"].notna()
    ]
    if len(cmp_):
        last = cmp_[cmp_["roc_max"] == cmp_["roc_max"].max()]
        print(
            "Paired comparisons with rank fusion (Table S, RoC-max "
            f"{last['roc_max'].iloc[0]:.2f}; all tables: comparisons.md):"
        )
        for r in last.itertuples():
            print(
                f"  {r.method} - rank_fusion = {r.diff:+.2f} [{r.diff_ci_low:+.2f}, "
                f"{r.diff_ci_high:+.2f}]"
                + (
                    f", sign flips in {100 * r.sign_flip_share:.0f}% of resamples"
                    if r.sign_flip_share == r.sign_flip_share
                    else ""
                )
            )


def cmd_report(args: argparse.Namespace) -> int:
    """``harness report``: (re)write ``report.html`` of an earlier run."""
    from .outdirs import claim_dir, read_run_record, run_lock
    from .report_html import write_html_report

    if args.gallery is not None and args.gallery < 0:
        raise HarnessError(f"--gallery {args.gallery}: must be >= 0")
    out = Path(args.out)
    read_run_record(out)  # a finished run, its record readable
    out = claim_dir(out, "run")  # a run directory the harness wrote, nothing else
    with run_lock(out):
        path = write_html_report(out, args.gallery)
    print(f"report: {path}")
    return 0


def cmd_annotations(args: argparse.Namespace) -> int:
    """``harness annotations``: export frames for labelling or import a labelled set."""
    from .annotations import export_for_labelling, import_annotations

    if args.action == "import":
        frames = None
        if args.frames:
            from .ingest import load_frames

            frames = load_frames(Path(args.frames))
        df = import_annotations(
            args.format, Path(args.src), frames, Path(args.out), force=args.force
        )
        print(f"{len(df)} annotation rows -> {args.out}")
        return 0
    import pandas as pd

    from .ingest import load_frames
    from .inputs import check_input
    from .outdirs import check_replaceable

    check_replaceable(Path(args.out), "labelling-task", args.force)  # before reading anything
    pairs_path = check_input(args.pairs, "pair table", HarnessError)
    try:
        pairs = pd.read_parquet(pairs_path)
    except (OSError, ValueError) as err:
        raise HarnessError(f"{pairs_path}: not a readable parquet pair table ({err})") from None
    need = ["q_session", "q_camera", "q_utime", "r_session", "r_camera", "r_utime"]
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


def cmd_inspect(args: argparse.Namespace) -> int:
    """``harness inspect``: topics, image encodings and the tf tree of a log."""
    import json

    from rich.console import Console
    from rich.table import Table

    from .log_inspect import inspect_log

    info = inspect_log(Path(args.log))
    if args.json:
        print(json.dumps(info, indent=2, default=str))
        return 0
    console = Console(width=max(Console().width, 140))
    console.print(f"[bold]{info['path']}[/] ({info['format']})")
    if info["format"] == "nclt":
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
    from .cache_gc import collect_garbage

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


def build_parser() -> argparse.ArgumentParser:
    """The ``harness`` argument parser: one subcommand per stage."""
    ap = argparse.ArgumentParser(
        prog="harness", description="Detection-by-Localization benchmark harness"
    )
    ap.add_argument("-v", "--verbose", action="store_true")
    sub = ap.add_subparsers(dest="cmd", required=True)

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
        p.add_argument("--seed", type=int)
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

    p = sub.add_parser(
        "detect", help="what changed: the detector on new sessions against a map session"
    )
    p.add_argument("--config", required=True, help="sessions, localizer(s); annotations optional")
    p.add_argument("--map", required=True, help="the map (reference) session")
    p.add_argument(
        "--query", required=True, action="append", help="a new session (repeat for several)"
    )
    p.add_argument("--out", required=True)
    p.add_argument("--data-root", help="replaces {data_root} and data_root in the config")
    p.add_argument("--seed", type=int)
    p.add_argument(
        "--method",
        default="rank_fusion",
        help="the rank method whose LoC finds the boxes (rank_fusion, rank_fusion_le2, _le3)",
    )
    p.add_argument("--nms-iou", type=float, default=0.5)
    p.add_argument("--max-boxes", type=int, default=10, help="change boxes per frame at most")
    p.add_argument("--top", type=int, default=10, help="most changed places shown")
    p.add_argument("--executor", choices=["local", "ray"], default="local")
    p.add_argument("--address", help="Ray cluster address (default: start a local cluster)")
    p.add_argument("--ray-cpus", type=int, help="workers of a local Ray cluster")
    p.set_defaults(func=cmd_detect)

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
    p.add_argument("--seed", type=int)
    p.add_argument(
        "--images",
        choices=["upright", "source"],
        default="upright",
        help="upright: write rotated frames upright as PNG (default); source: name the stored "
        "files with a rotation column",
    )
    p.set_defaults(func=cmd_task, executor="local", address=None, ray_cpus=None)

    p = sub.add_parser("report", help="(re)write OUT/report.html for an existing run")
    p.add_argument("out", help="a run directory (the --out of harness reproduce)")
    p.add_argument(
        "--gallery",
        type=int,
        help="thumbnails per method and kind (default: the run's [report] gallery)",
    )
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("gc", help="remove the cache entries of OUT that its last run did not use")
    p.add_argument("out", help="a run directory (the --out of harness reproduce)")
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="list what would be removed, and its size; remove nothing",
    )
    p.set_defaults(func=cmd_gc)

    p = sub.add_parser(
        "inspect",
        help="what is in a log: topics, rates, images, the tf tree, and config lines to ingest it",
    )
    p.add_argument("log", help="an NCLT root, a .bag, a ROS2 bag directory or an .mcap")
    p.add_argument("--json", action="store_true", help="print the description as JSON")
    p.set_defaults(func=cmd_inspect)

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
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; library errors become one ``ERROR:`` line.

    Returns:
        The exit status: 0, or 1 after an error.
    """
    args = build_parser().parse_args(argv)
    _setup_logging(args.verbose)
    try:
        return int(args.func(args))
    except HarnessError as err:
        print(f"ERROR: {err}", file=sys.stderr)
        return 1
    except OSError as err:
        if err.errno not in _FS_ERRORS:
            raise
        where = err.filename or "an output file"
        print(f"ERROR: {where}: {err.strerror or err}; {_FS_ERRORS[err.errno]}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            "ERROR: interrupted; completed stages are cached, rerun the same command to resume",
            file=sys.stderr,
        )
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""``harness``: one subcommand per stage plus ``reproduce``. Library errors become one ``ERROR:`` line and exit 1."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path

from .errors import HarnessError

log = logging.getLogger("harness")


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
    from .fixture import FixtureSpec, generate

    spec = FixtureSpec(seed=args.seed, frames=args.frames, width=args.width, height=args.height, objects=args.objects,
                       loop_scale=args.loop_scale, render_scale=args.render_scale)
    formats = args.formats.split(",") if args.formats else None
    try:
        out = generate(Path(args.out), spec, all_formats=args.all_formats, formats=formats)
    except ValueError as err:
        raise HarnessError(f"harness fixture: {err}") from None
    print(f"fixture written to {out} (annotations: {out / 'annotations.csv'})")
    return 0


def cmd_ingest(args: argparse.Namespace) -> int:
    from .config import IngestConfig, SessionConfig
    from .ingest import ingest_session

    if args.config:
        cfg = _config(args)
        sessions, ic = cfg.sessions, cfg.ingest
        if args.salvage:
            ic = dataclasses.replace(ic, salvage=True)
        for sc in sessions:
            rep = ingest_session(sc, ic, Path(args.out) / sc.name)
            print(f"{sc.name}: {rep['frames_written']} frames -> {Path(args.out) / sc.name / 'frames.parquet'}")
        return 0
    if not args.source or not args.session:
        raise HarnessError("ingest needs SOURCE and --session NAME, or --config FILE")
    sc = SessionConfig(name=args.session, source=str(Path(args.source).resolve()), camera=args.camera,
                       image_topic=args.image_topic, pose_topic=args.pose_topic, tf_child_frame=args.tf_child_frame)
    ic = IngestConfig(max_pose_gap_s=args.max_pose_gap, time_source=args.time_source, salvage=args.salvage)
    rep = ingest_session(sc, ic, Path(args.out))
    print(f"{rep['frames_written']} frames -> {Path(args.out) / 'frames.parquet'}; report: {Path(args.out) / 'ingest_report.json'}")
    print(f"dropped: {rep['dropped']}")
    return 0


def _pipeline(args: argparse.Namespace):
    from .runner import Pipeline

    return Pipeline(_config(args), Path(args.out), rank_import=Path(args.rank_import) if getattr(args, "rank_import", None) else None)


def cmd_pairs(args: argparse.Namespace) -> int:
    p = _pipeline(args)
    *_, pairs, key = p.until_pairs()
    d = p.cache.path("pairs", key)
    print(f"{len(pairs)} pairs -> {d / 'pairs.parquet'}\n{(d / 'summary.json').read_text()}")
    return 0


def cmd_proposals(args: argparse.Namespace) -> int:
    p = _pipeline(args)
    p.fixture()
    ing = p.ingest()
    frames, _ = p.frames(ing)
    for s, (df, key) in p.proposals(frames, ing).items():
        print(f"{s}: {len(df)} proposals {df.groupby('method').size().to_dict()} -> {p.cache.path('proposals', key) / 'proposals.parquet'}")
    return 0


def cmd_rank(args: argparse.Namespace) -> int:
    p = _pipeline(args)
    ing, frames, _, _, _, pairs, pkey = p.until_pairs()
    described = {}
    if p.rank_import is None:
        props = p.proposals(frames, ing)
        described = p.describe(frames, props, p.train(frames, props))
    ranks, _, counts = p.ranks(frames, pairs, pkey, described)
    from .cache import write_json, write_parquet

    write_parquet(Path(args.out) / "ranks.parquet", ranks)
    write_json(Path(args.out) / "rank_report.json", counts)
    print(f"{len(ranks)} ranked query subimages -> {Path(args.out) / 'ranks.parquet'}; counts: {counts}")
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from .runner import METHOD_LABELS

    rec = _pipeline(args).run()
    table = rec["table"]
    t = Table(title=f"Table I: AP by RoC-max ({rec['config']['name']})")
    t.add_column("AP")
    for c in table.columns:
        t.add_column(f"{c:.2f}", justify="right")
    for m, row in table.iterrows():
        t.add_row(METHOD_LABELS[m], *("NaN" if v != v else f"{v:.2f}" for v in row.to_numpy()))
    Console().print(t)
    print(f"reports in {Path(args.out)}: table1.md, table1.csv, splits/, plots/, locmaps/, run.json ({rec['total_s']:.1f} s)")
    return 0


def cmd_annotations(args: argparse.Namespace) -> int:
    from .annotations import export_for_labelling, import_annotations

    if args.action == "import":
        frames = None
        if args.frames:
            from .ingest import load_frames

            frames = load_frames(Path(args.frames))
        df = import_annotations(args.format, Path(args.src), frames, Path(args.out))
        print(f"{len(df)} annotation rows -> {args.out}")
        return 0
    import pandas as pd

    from .ingest import load_frames

    pairs = pd.read_parquet(args.pairs)
    out = export_for_labelling(pairs, load_frames(Path(args.frames)), Path(args.out), args.limit)
    print(f"labelling task written to {out} (task.json + images/)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="harness", description="Detection-by-Localization benchmark harness")
    ap.add_argument("-v", "--verbose", action="store_true")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("fixture", help="generate the synthetic fixture world as real logs")
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=64, help="frames per session")
    p.add_argument("--width", type=int, default=120)
    p.add_argument("--height", type=int, default=160)
    p.add_argument("--objects", type=int, default=3, help="change objects per changed session")
    p.add_argument("--loop-scale", type=float, default=1.5, help="size of the loop road (1.0: 60 m x 40 m)")
    p.add_argument("--render-scale", type=int, default=1, help="ray-cast at 1/scale resolution, then upsample (fast large frames)")
    p.add_argument("--formats", default=None, help="comma-separated log format per session (one name: all sessions), e.g. ros2")
    p.add_argument("--all-formats", action="store_true", help="write every session in every log format")
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
    p.add_argument("--tf-child-frame")
    p.add_argument("--time-source", choices=["header", "log"], default="header")
    p.add_argument("--max-pose-gap", type=float, default=0.1, help="seconds")
    p.add_argument("--salvage", action="store_true", help="keep the frames read before a damaged part of a log")
    p.set_defaults(func=cmd_ingest)

    for name, func, hlp in (("pairs", cmd_pairs, "build cross-season pairs"), ("proposals", cmd_proposals, "compute object proposals"),
                            ("rank", cmd_rank, "ranks of the ground-truth reference per query subimage"),
                            ("reproduce", cmd_reproduce, "run the whole pipeline and write Table I")):
        p = sub.add_parser(name, help=hlp)
        p.add_argument("--config", required=True)
        p.add_argument("--out", required=True)
        p.add_argument("--data-root", help="replaces {data_root} and data_root in the config")
        p.add_argument("--seed", type=int)
        p.add_argument("--executor", choices=["local", "ray"], default="local", help="where stage units run (ray: pip install 'dbl-harness[ray]')")
        p.add_argument("--address", help="Ray cluster address (default: start a local cluster)")
        p.add_argument("--ray-cpus", type=int, help="workers of a local Ray cluster")
        if name in ("rank", "reproduce"):
            p.add_argument("--import", dest="rank_import", help="ranked lists from an external localizer (see docs)")
        p.set_defaults(func=func)

    p = sub.add_parser("annotations", help="import annotations from labelling tools, or export a labelling task")
    asub = p.add_subparsers(dest="action", required=True)
    pi = asub.add_parser("import")
    pi.add_argument("format", choices=["coco", "voc", "cvat"])
    pi.add_argument("src")
    pi.add_argument("--out", required=True)
    pi.add_argument("--frames", help="frames.parquet to validate against")
    pi.set_defaults(func=cmd_annotations)
    pe = asub.add_parser("export")
    pe.add_argument("--pairs", required=True)
    pe.add_argument("--frames", required=True)
    pe.add_argument("--out", required=True)
    pe.add_argument("--limit", type=int)
    pe.set_defaults(func=cmd_annotations)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args.verbose)
    try:
        return int(args.func(args))
    except HarnessError as err:
        print(f"ERROR: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("ERROR: interrupted; completed stages are cached, rerun the same command to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

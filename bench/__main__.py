"""``python -m bench [--quick] [--only CASE ...]``: stage throughput and peak memory.

Each case runs in its own subprocess so that its peak resident memory (ru_maxrss) is its own.
Results: ``results/bench/bench.json`` (all runs) and ``results/bench/bench.md`` (medians).
Bench data is generated under ``bench/.data/`` (not in git).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

from harness.runtime.cache import atomic_path

from .cases import CASES, measures
from .provenance import staleness, stamp

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "bench" / ".data"
OUT = ROOT / "results" / "bench"

HIDDEN = {
    "case",
    "median",
    "unit",
    "runs",
    "peak_rss_mib",
    "notes",
    "group",
    "points",
    "table_l",
    "commit",
    "dirty",
    "date",
    "cpu",
}


def run_case(name: str, quick: bool) -> list[dict]:
    cmd = [sys.executable, "-m", "bench.cases", name] + (["--quick"] if quick else [])
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        raise SystemExit(f"bench case {name} failed")
    prov = stamp(measures(name))
    return [
        {**json.loads(line), "group": name, **prov}
        for line in proc.stdout.splitlines()
        if line.startswith("{")
    ]


def measured(r: dict) -> str:
    """A row's provenance cell: commit (+dirty), date and CPU, or what it lacks."""
    if not r.get("commit"):
        return "not recorded"
    dirty = "+dirty" if r.get("dirty") else ""
    return f"{r['commit'][:8]}{dirty}, {str(r.get('date', '?'))[:10]}, {r.get('cpu', '?')}"


def plot_scaling(rows: list[dict], path: Path) -> None:
    """Log-log plot of every scaling series, one panel per x quantity, with the fitted exponent."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = sorted({r["points"]["xlabel"] for r in rows})
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.5), squeeze=False)
    for ax, xl in zip(axes[0], panels, strict=True):
        for r in (r for r in rows if r["points"]["xlabel"] == xl):
            ax.loglog(
                r["points"]["x"],
                r["points"]["y"],
                "o-",
                label=f"{r['case'].removeprefix('scaling: ').split(' vs ')[0]} (exp "
                f"{r['median']:.2f})",
            )
        ax.set_xlabel(xl)
        ax.set_ylabel(
            " / ".join(sorted({r["points"]["ylabel"] for r in rows if r["points"]["xlabel"] == xl}))
        )
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller sizes (a smoke run)")
    ap.add_argument("--only", nargs="*", choices=CASES)
    ap.add_argument(
        "--render", action="store_true", help="rewrite bench.md from bench.json, running nothing"
    )
    args = ap.parse_args()
    rows = []
    if args.render:
        rows = json.loads((OUT / "bench.json").read_text())["results"]
    elif args.only and (OUT / "bench.json").exists():  # keep the other cases' latest figures
        rows = [
            r
            for r in json.loads((OUT / "bench.json").read_text())["results"]
            if r.get("group") not in args.only
        ]
    for case in [] if args.render else args.only or CASES:
        t0 = time.perf_counter()
        got = run_case(case, args.quick)
        rows += got
        print(f"{case}: {len(got)} result(s) in {time.perf_counter() - t0:.1f} s", flush=True)
        for r in got:
            print("   ", r["case"], {k: v for k, v in r.items() if k not in ("case", "runs")})
    OUT.mkdir(parents=True, exist_ok=True)
    if not args.render:
        write_json(rows)
    write_md(rows)
    return 0


def write_json(rows: list[dict]) -> None:
    meta = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": __import__("os").cpu_count(),
    }
    with atomic_path(OUT / "bench.json") as tmp:
        tmp.write_text(json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")


def write_md(rows: list[dict]) -> None:
    lines = [
        "Each row says where it was measured (commit, date, CPU) and whether the code its case",
        "measures (`CASES` in `bench/cases/__init__.py`) changed after that commit, beyond its",
        "docstrings and comments: a **stale** row is a figure of older code, kept until its case",
        "runs again (`python -m bench --only CASE`).",
        "",
        "| case | median | unit | peak RSS MiB | measured at | stale | notes |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["unit"] == "exponent":
            continue
        extra = "; ".join(f"{k} {v}" for k, v in r.items() if k not in HIDDEN)
        notes = "; ".join(x for x in (r.get("notes", ""), extra) if x)
        stale = staleness(r, measures(r.get("group", "")))
        lines.append(
            f"| {r['case']} | {r['median']:.4g} | {r['unit']} | "
            f"{r.get('peak_rss_mib', float('nan')):.0f} | {measured(r)} | {stale} | {notes} |"
        )
    scaling = [r for r in rows if r["unit"] == "exponent"]
    if scaling:
        lines += [
            "",
            "## Scaling (cost ~ work ** exponent, least squares in log-log; plot: scaling.png)",
            "",
            "| what | fitted exponent | points (x: y) |",
            "|---|---|---|",
        ]
        for r in scaling:
            pts = ", ".join(
                f"{x:g}: {y:.3g}" for x, y in zip(r["points"]["x"], r["points"]["y"], strict=True)
            )
            lines.append(
                f"| {r['case'].removeprefix('scaling: ')} | {r['median']:.2f} | {pts} "
                f"({r['points']['ylabel']}) |"
            )
        plot_scaling(scaling, OUT / "scaling.png")
    proj = [r for r in rows if r["case"].startswith("full-nclt projection: ")]
    if proj:
        lines += [
            "",
            (
                "## Full NCLT (100,000 frames, 1.6 M subimages, 5,242 query images): measured "
                "rates, projected times"
            ),
            "",
            (
                "Rates measured in this run (case full-nclt; ranking at full size, the other "
                "stages on the NCLT-scale"
            ),
            (
                "workload with `bench/nclt_full.toml`), projected linearly to the whole NCLT: "
                "ingest over every"
            ),
            (
                "frame, proposals and descriptors over the frames a run describes (query frames "
                "and the reference"
            ),
            (
                "frames a `db_stride_m` database keeps; see the notes under the table for the "
                "assumption)."
            ),
            "",
            "| stage | measured | unit | projected, CPU (min) | its kernels' limit (min) "
            "| x the limit | projected, GPU |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in proj:
            name = r["case"].removeprefix("full-nclt projection: ")
            lim = r.get("limit_min_cpu")
            vs = r.get("vs_limit")
            rated = f"{lim:.1f} | {vs:.2f}x" if lim else "not rated | "
            if name == "total":
                lines.append(
                    f"| **total** | | | **{60 * r['median']:.0f} min = {r['median']:.2f} "
                    "h** | | | not measured: no GPU lent |"
                )
            elif "projected_min_cpu" not in r:  # the rated stages' sum against their limits
                lines.append(f"| *{name}* | | | {r['median']:.1f} | {rated} | not measured |")
            else:
                lines.append(
                    f"| {name} | {r['median']:.4g} | {r['unit']} | "
                    f"{r['projected_min_cpu']:.1f} | {rated} | not measured |"
                )
        tot = next((r for r in proj if r["case"].endswith("total")), None)
        if tot:
            lines += ["", tot["notes"]]
    with atomic_path(OUT / "bench.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    print((OUT / "bench.md").read_text())


if __name__ == "__main__":
    raise SystemExit(main())

"""``python -m bench.detect_choice [--sets fixture,obchange-dev,world] [--out DIR]``: the choice
of ``harness detect``'s default, by the rule written down before any figure of the held-out
world was seen (docs/method.md, *Keypoint localization*):

    the configuration with the largest minimum, over the sets, of Table D's detector AP50 less
    the top of its chance band.

Every candidate (what ranks the subimages x whose boxes x the box prior) runs ``harness detect``
as a user types it on each set; the table of every candidate on every set, failures included,
is printed (markdown) and written to ``OUT/detect_choice.md`` and ``.json``. The sets:

- ``fixture``: the bundled fixture, ``--map 2012-01-22 --query 2012-03-31 --query 2012-08-04``;
- ``obchange-dev``: ``../shared/realdata/obchange-dev`` (real robot revisits; skipped, saying so,
  where the folder is absent; its images never enter the repository);
- ``world``: a generated world of 240 x 320 frames (seed 12, 160 frames a session, loop scale
  3: 64 annotated frames, 31 change boxes over its three query sessions), generated under
  ``bench/.data/``, held out until the candidates and the rule were fixed.
"""

from __future__ import annotations

import argparse
import itertools
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "realdata"
DATA = ROOT / "bench" / ".data"

#: The candidates: (--localizer, --proposals, --box-prior).
CANDIDATES = list(
    itertools.product(("local", "keypoints"), ("segments", "selective"), ("area", "difference"))
)
#: The held-out world: (seed, frames a session, width, height, loop scale).
WORLD = (12, 160, 240, 320, 3.0)


def _world() -> tuple[list[str], str]:
    """The held-out world's config (generated once under bench/.data) and its sessions."""
    seed, frames, w, h, loop = WORLD
    root = DATA / f"world-{w}x{h}-s{seed}"
    cfg = DATA / f"world-{w}x{h}-s{seed}.toml"
    text = (ROOT / "datasets" / "fixture.toml").read_text()
    text = text.replace('data_root = "datasets/fixture"', f'data_root = "{root}"')
    text = text.replace(
        'annotations = "annotations/fixture.csv"', f'annotations = "{root}/annotations.csv"'
    )
    text = text.replace('trained_models = "datasets/models"', "")
    start = text.index("[fixture]")
    end = text.index("\n[", start + 1)
    text = (
        text[:start]
        + (
            f"[fixture]\ngenerate = true\nseed = {seed}\nframes = {frames}\nwidth = {w}\n"
            f"height = {h}\nobjects = 9\nloop_scale = {loop}\n"
        )
        + text[end:]
    )
    DATA.mkdir(parents=True, exist_ok=True)
    cfg.write_text(text)
    return ["--config", str(cfg), "--map", "2012-01-22", "--query", "2012-03-31",
            "--query", "2012-08-04", "--query", "2012-11-17"], str(cfg)  # fmt: skip


def set_args(name: str) -> list[str] | None:
    """The arguments that name a set, or None where it is not here."""
    if name == "fixture":
        return ["--config", str(ROOT / "datasets" / "fixture.toml"), "--map", "2012-01-22",
                "--query", "2012-03-31", "--query", "2012-08-04"]  # fmt: skip
    if name == "obchange-dev":
        d = REAL / "obchange-dev"
        if not d.is_dir():
            return None
        return ["--map-images", str(d / "A"), "--query-images", str(d / "B"),
                "--annotations", str(d / "annotations.csv")]  # fmt: skip
    if name == "world":
        return _world()[0]
    raise SystemExit(f"ERROR: unknown set {name!r}: fixture, obchange-dev or world")


def run_one(set_name: str, args: list[str], cand: tuple[str, str, str], out: Path) -> dict:
    """One candidate on one set: Table D's detector row (or what failed)."""
    loc, props, prior = cand
    dst = out / set_name / "-".join(cand)
    # the alarms' calibration does not enter Table D's AP: within the run, no null is scored
    cmd = [sys.executable, "-m", "harness.cli", "detect", *args, "--localizer", loc,
           "--proposals", props, "--box-prior", prior, "--calibration", "within-run",
           "--out", str(dst)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    row = {"set": set_name, "localizer": loc, "proposals": props, "box_prior": prior}
    if proc.returncode != 0 or not (dst / "tableD.csv").is_file():
        return {**row, "error": (proc.stderr.strip().splitlines() or ["no Table D"])[-1]}
    t = pd.read_csv(dst / "tableD.csv")
    d = t[t["row"] == "detector"].iloc[0]
    diff = t[t["row"].str.startswith("aligned difference")]
    return {
        **row,
        "ap50": float(d["ap50_voc_all_point"]),
        "chance_high": float(d["chance_high"]),
        "margin": float(d["ap50_voc_all_point"] - d["chance_high"]),
        "verdict": str(d["verdict"]),
        "recall": float(d["candidate_recall"]),
        "aligned_difference": float(diff["ap50_voc_all_point"].iloc[0]) if len(diff) else None,
    }


def choose(rows: list[dict]) -> tuple[str, str, str] | None:
    """The rule: the largest minimum over the sets of AP50 less the chance band's top."""
    df = pd.DataFrame([r for r in rows if "margin" in r])
    if df.empty:
        return None
    worst = df.groupby(["localizer", "proposals", "box_prior"])["margin"].min()
    full = df.groupby(["localizer", "proposals", "box_prior"])["set"].nunique()
    worst = worst[full == full.max()]  # a candidate that failed on a set is not chosen
    return tuple(worst.sort_values(ascending=False, kind="stable").index[0])  # type: ignore[return-value]


def markdown(rows: list[dict]) -> str:
    """Every candidate on every set: AP50 / chance band's top (verdict), candidates' recall."""
    sets = sorted({r["set"] for r in rows}, key=["fixture", "obchange-dev", "world"].index)
    head = "| localizer | proposals | box prior | " + " | ".join(sets) + " | min margin |"
    lines = [head, "|---|---|---|" + "---:|" * (len(sets) + 1)]
    for cand in [c for c in CANDIDATES if any(
            (r["localizer"], r["proposals"], r["box_prior"]) == c for r in rows)]:  # fmt: skip
        cells, margins = [], []
        for s in sets:
            r = next((x for x in rows if x["set"] == s and
                      (x["localizer"], x["proposals"], x["box_prior"]) == cand), None)  # fmt: skip
            if r is None or "error" in r:
                cells.append(f"failed: {r['error'][:60]}" if r else "-")
                continue
            mark = {"above": " ▲", "below": " ▼", "baseline": " △"}.get(r["verdict"], " ○")
            cells.append(
                f"{r['ap50']:.3f} / {r['chance_high']:.3f}{mark} (recall {r['recall']:.2f})"
            )
            margins.append(r["margin"])
        worst = f"{min(margins):+.3f}" if len(margins) == len(sets) else "-"
        lines.append(f"| {' | '.join(cand)} | " + " | ".join(cells) + f" | {worst} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="fixture,obchange-dev,world")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "detect_choice")
    ap.add_argument(
        "--candidates",
        default="",
        help="only these candidates, LOCALIZER/PROPOSALS/PRIOR separated by commas (default: all)",
    )
    a = ap.parse_args(argv)
    cands = CANDIDATES
    if a.candidates:
        cands = [tuple(c.split("/")) for c in a.candidates.split(",")]  # type: ignore[misc]
        bad = [c for c in cands if c not in CANDIDATES]
        if bad:
            print(f"ERROR: --candidates {'/'.join(bad[0])}: not one of "
                  f"{', '.join('/'.join(c) for c in CANDIDATES)}", file=sys.stderr)  # fmt: skip
            return 1
    rows = []
    for s, args in sets_here(a.sets):
        for cand in cands:
            rows.append(run_one(s, args, cand, a.out))
            print(json.dumps(rows[-1]), flush=True)
    md = markdown(rows)
    pick = choose(rows)
    md += f"\nChosen by the rule: {' / '.join(pick) if pick else 'none'}\n"
    write_table(a.out, "detect_choice", rows, md)
    return 0


def sets_here(names: str) -> list[tuple[str, list[str]]]:
    """The sets of ``names`` (comma-separated) with their arguments; each one absent said so."""
    here = []
    for s in names.split(","):
        args = set_args(s)
        if args is None:
            print(f"skipped {s}: {REAL / s} is not here (real pairs are read from shared/, never "
                  "kept in the repository)")  # fmt: skip
            continue
        here.append((s, args))
    return here


def write_table(out: Path, stem: str, rows: list[dict], md: str) -> None:
    """``OUT/STEM.md`` (the table) and ``OUT/STEM.json`` (every row), and the table printed."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.md").write_text(md)
    (out / f"{stem}.json").write_text(json.dumps(rows, indent=1))
    print(md)


if __name__ == "__main__":
    raise SystemExit(main())

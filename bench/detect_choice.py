"""``python -m bench.detect_choice [--sets obchange-rooms,world,fixture] [--out DIR]``: the
choice of ``harness detect``'s default, by the rule written down before the candidates were run
(docs/decisions.md, *Choosing the default*):

    among the candidates whose detector row is above chance on the generated world of 240 x 320
    frames, the one with the largest lower end of its grouped 95% interval of AP50 over every
    annotated frame of obchange-rooms. The plain difference alone (Table D's row of that name,
    the same in every run) is a candidate too.

Every candidate (what ranks the subimages x whose boxes x the box prior) runs ``harness detect``
as a user types it on each set; the table of every candidate on every set, failures included,
is printed (markdown) and written to ``OUT/detect_choice.md`` and ``.json``. The sets:

- ``obchange-rooms``: ``../shared/realdata/obchange-rooms`` (51 real robot revisits of two rooms;
  skipped, saying so, where the folder is absent; its images never enter the repository);
- ``obchange-dev``: ten of those pairs;
- ``world``: a generated world of 240 x 320 frames (seed 12, 160 frames a session, loop scale
  3: 64 annotated frames, 31 change boxes over its three query sessions), generated under
  ``bench/.data/``;
- ``fixture``: the bundled fixture, ``--map 2012-01-22 --query 2012-03-31 --query 2012-08-04``:
  the Table I regression's world of 120 x 160 frames; printed, never deciding.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "realdata"
DATA = ROOT / "bench" / ".data"

#: The difference's settings a candidate runs with (``[detect]`` and ``[detect.difference]``):
#: the recipe (contrast with a ring half the box wide; a pair that cannot be registered dropped),
#: the ratio to a ring a quarter wide, a pair that cannot be registered compared as it stands;
#: each with the difference alone or times the colours' novelty.
SETTINGS = {
    "contrast-drop": {"not_comparable": "drop", "box_score": "contrast", "ring": 0.5},
    "contrast-fallback": {"not_comparable": "fallback", "box_score": "contrast", "ring": 0.5},
    "ratio-drop": {"not_comparable": "drop", "box_score": "ratio", "ring": 0.25},
    "ratio-fallback": {"not_comparable": "fallback", "box_score": "ratio", "ring": 0.25},
}
SETTINGS = {
    **{k: {**v, "colour": "none"} for k, v in SETTINGS.items()},
    **{f"{k}-novelty": {**v, "colour": "novelty"} for k, v in SETTINGS.items() if "ratio" in k},
}
#: The last with NMS's overlap below the evaluation's IoU of 0.5, or the localizer's score
#: squared or to the fourth power in the product (``[detect] localization_weight``; 1 above).
SETTINGS |= {
    "ratio-fallback-novelty-nms0.3": {**SETTINGS["ratio-fallback-novelty"], "nms_iou": 0.3},
    **{
        f"ratio-fallback-novelty-w{w}": {**SETTINGS["ratio-fallback-novelty"], "weight": w}
        for w in (2, 4)
    },
}
#: The earlier recipe's settings above name it; the reference recipe (harness.detect.plain: its
#: own registration, change map, boxes and ring; the pair dropped or read by its colours), its
#: difference alone or times the localizer's score to the first or fourth power.
SETTINGS = {k: {**v, "recipe": "novelty-product"} for k, v in SETTINGS.items()}
SETTINGS |= {
    f"reference-w{w}": {
        "recipe": "reference", "not_comparable": "fallback", "box_score": "contrast",
        "ring": 0.25, "colour": "none", "weight": w,
    }
    for w in (1, 4)
}  # fmt: skip
#: The candidates: (--localizer, --proposals, --box-prior, settings); each run also gives the
#: plain difference alone under its settings, its Table D row.
CANDIDATES = [
    *(("keypoints", "selective", "difference_product", s) for s in SETTINGS),
    ("keypoints", "selective", "difference", "ratio-fallback"),
    ("local", "selective", "difference_product", "ratio-fallback"),
    ("local", "selective", "difference_product", "ratio-fallback-novelty"),
    ("keypoints", "segments", "area", "contrast-drop"),
    ("local", "selective", "difference_product", "reference-w4"),
]
PLAIN = ("none", "selective", "plain difference")
#: Where the real sets lie, and the set that decides.
REAL_SETS = ("obchange-rooms", "obchange-dev")
DECIDES = "obchange-rooms"
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
    if name in REAL_SETS:
        d = REAL / name
        if not d.is_dir():
            return None
        return ["--map-images", str(d / "A"), "--query-images", str(d / "B"),
                "--annotations", str(d / "annotations.csv")]  # fmt: skip
    if name == "world":
        return _world()[0]
    raise SystemExit(f"ERROR: unknown set {name!r}: obchange-rooms, obchange-dev, world or fixture")


def settings_toml(name: str) -> str:
    """The ``[detect]`` and ``[detect.difference]`` tables of a candidate's settings."""
    st = SETTINGS[name]
    return (
        f'\n[detect]\nnot_comparable = "{st["not_comparable"]}"\n'
        f"nms_iou = {st.get('nms_iou', 0.5)}\nlocalization_weight = {st.get('weight', 1)}\n"
        f'\n[detect.difference]\nrecipe = "{st["recipe"]}"\n'
        f'box_score = "{st["box_score"]}"\nring = {st["ring"]}\ncolour = "{st["colour"]}"\n'
    )


def with_settings(args: list[str], name: str, dst: Path) -> list[str]:
    """``args`` with a config carrying the candidate's settings (the set's own config, or the
    settings alone for two folders), written beside the run directory ``dst``."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    cfg = dst.parent / f"{dst.name}.toml"
    if "--config" in args:
        i = args.index("--config") + 1
        base = Path(args[i])
        text = base.read_text().replace('data_root = "datasets/', f'data_root = "{ROOT}/datasets/')
        text = text.replace('annotations = "annotations/', f'annotations = "{ROOT}/annotations/')
        text = text.replace('trained_models = "datasets/', f'trained_models = "{ROOT}/datasets/')
        cfg.write_text(text + settings_toml(name))
        return [*args[:i], str(cfg), *args[i + 1 :]]
    cfg.write_text(settings_toml(name))
    return ["--config", str(cfg), *args]


def run_one(set_name: str, args: list[str], cand: tuple[str, ...], out: Path) -> dict:
    """One candidate on one set: Table D's detector row (or what failed)."""
    loc, props, prior, settings = cand
    dst = out / set_name / "-".join(cand)
    args = with_settings(args, settings, dst)
    # the alarms' calibration does not enter Table D's AP: within the run, no null is scored
    cmd = [sys.executable, "-m", "harness.cli", "detect", *args, "--localizer", loc,
           "--proposals", props, "--box-prior", prior, "--calibration", "within-run",
           "--out", str(dst)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    row = {"set": set_name, "localizer": loc, "proposals": props, "box_prior": prior,
           "settings": settings}  # fmt: skip
    if proc.returncode != 0 or not (dst / "tableD.csv").is_file():
        return {**row, "error": (proc.stderr.strip().splitlines() or ["no Table D"])[-1]}
    t = pd.read_csv(dst / "tableD.csv")
    d = t[t["row"] == "detector"].iloc[0]
    plain = t[t["row"].str.startswith("plain difference, registered")]
    out = {**row, **_figures(d)}
    if len(plain):
        out["plain"] = _figures(plain.iloc[0])
        out["vs_plain"] = [float(d["vs_plain_ci_low"]), float(d["vs_plain_ci_high"])]
    return out


def _figures(d: pd.Series) -> dict:
    """A Table D row's AP50, interval, chance band's top, verdict and candidates' recall."""
    return {
        "ap50": float(d["ap50_voc_all_point"]),
        "ci_low": float(d["ci_low"]),
        "ci_high": float(d["ci_high"]),
        "chance_high": float(d["chance_high"]),
        "margin": float(d["ap50_voc_all_point"] - d["chance_high"]),
        "verdict": str(d["verdict"]),
        "recall": float(d["candidate_recall"]),
        "groups": int(d["groups"]) if "groups" in d else None,
    }


def _flat(rows: list[dict]) -> list[dict]:
    """Each run's detector row, and the plain difference as a candidate of its own (once a set
    and settings)."""
    out, seen = [], set()
    for r in rows:
        out.append(r)
        if "plain" in r and (r["set"], r["settings"]) not in seen:
            seen.add((r["set"], r["settings"]))
            out.append({"set": r["set"], **dict(zip(("localizer", "proposals", "box_prior"),
                                                     PLAIN, strict=True)),
                        "settings": r["settings"], **r["plain"]})  # fmt: skip
    return out


def choose(rows: list[dict]) -> tuple[str, ...] | None:
    """The rule: above chance on the world, then the largest grouped lower end on the rooms."""
    df = pd.DataFrame([r for r in _flat(rows) if "ap50" in r])
    if df.empty or DECIDES not in set(df["set"]):
        return None
    key = ["localizer", "proposals", "box_prior", "settings"]
    ok = df[(df["set"] == "world") & (df["verdict"].isin(["above", "baseline"]))]
    rooms = df[df["set"] == DECIDES]
    if "world" in set(df["set"]):
        rooms = rooms.merge(ok[key], on=key)
    if rooms.empty:
        return None
    best = rooms.sort_values(["ci_low", "ap50"], ascending=False, kind="stable").iloc[0]
    return tuple(str(best[k]) for k in key)


def markdown(rows: list[dict]) -> str:
    """Every candidate on every set: AP50 [grouped 95% interval] / chance band's top (verdict)."""
    order = [*REAL_SETS, "world", "fixture"]
    flat = _flat(rows)
    sets = sorted({r["set"] for r in flat}, key=order.index)
    head = "| localizer | proposals | box prior | settings | " + " | ".join(sets) + " |"
    lines = [head, "|---|---|---|---|" + "---:|" * len(sets)]
    plain = [(*PLAIN, s) for s in SETTINGS]
    for cand in [*CANDIDATES, *plain]:
        here = [x for x in flat if (x["localizer"], x["proposals"], x["box_prior"],
                                    x["settings"]) == cand]  # fmt: skip
        if not here:
            continue
        cells = []
        for s in sets:
            r = next((x for x in here if x["set"] == s), None)
            if r is None or "error" in r:
                cells.append(f"failed: {r['error'][:60]}" if r else "-")
                continue
            mark = {"above": " ▲", "below": " ▼", "baseline": " △"}.get(r["verdict"], " ○")
            cells.append(
                f"{r['ap50']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}] / "
                f"{r['chance_high']:.3f}{mark}"
            )
        lines.append(f"| {' | '.join(cand)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="obchange-rooms,world,fixture")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "detect_choice")
    ap.add_argument(
        "--candidates",
        default="",
        help="only these candidates, LOCALIZER/PROPOSALS/PRIOR/SETTINGS separated by commas "
        "(default: all)",
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
    why = "" if pick else f" ({DECIDES} was not run)" if DECIDES not in a.sets.split(",") else ""
    md += f"\nChosen by the rule: {' / '.join(pick) if pick else 'none'}{why}\n"
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

"""``python -m bench.pairing_truth [--out DIR]``: how often each pairing descriptor and mode pairs a
new session's frames with the right map frame, where poses give the truth (docs/folders.md).

``harness detect`` as a user types it (``--config``, ``--map``, three ``--query`` sessions), with
``[pairs] by`` set to each mode that needs no poses and ``[descriptor] name`` to each descriptor;
a pair is right within 10 m of the pose pair's map frame (``detect.json``'s
``pairing.agreement_with_pose_pairs``, with its exact 95% interval and the share a random map
frame would reach). Two worlds, made under ``bench/.data/``: the bundled fixture (seed 0, 64
frames a session) and another (seed 7, 128 frames a session); each has four traverses of one
loop, the first the map. Printed as markdown and written to ``OUT/pairing_truth.md`` and ``.json``.

A third case is real footage as it comes: ``../shared/realdata/nordland-dev`` (a train ride in
summer and winter, in step) with the winter frames renamed (no shared names), paired by sequence
with no ``--config``, as it stands and with the map's start made dark (17 frames of the camera
starting up: a faint blurred glow of a real frame and sensor noise), a black and a grey frame, a
stop (one frame repeated 20 times) and a tunnel at its end (13 dark frames) spliced in: a query
frame is right when its map frame shows the place within 2 frames of its own
(:func:`spliced_nordland`). Skipped, saying so, where the folder is absent.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from bench.detect_choice import DATA, REAL, ROOT, write_table

#: (name, fixture seed, frames a session).
WORLDS = (("fixture (seed 0)", 0, 64), ("another world (seed 7)", 7, 128))
#: The pairing descriptors: the training-free default for folders, and the paper's autoencoder.
DESCRIPTORS = ("seqslam", "autoencoder")
MODES = ("order", "retrieval", "sequence")


def _config(seed: int, frames: int, descriptor: str, mode: str) -> Path:
    """The fixture's config on world ``seed`` with ``descriptor`` and ``[pairs] by = mode``."""
    root = DATA / f"pairing-world-s{seed}-f{frames}"
    text = (ROOT / "datasets" / "fixture-detect.toml").read_text()
    text = text.replace('data_root = "datasets/fixture"', f'data_root = "{root}"')
    text = text.replace("seed = 0\nframes = 64", f"seed = {seed}\nframes = {frames}")
    text = text.replace('trained_models = "datasets/models"', "")
    lines = text.splitlines()
    out = []
    for line in lines:
        out.append(line)
        if line.strip() == "[pairs]":
            out.append(f'by = "{mode}"')  # detect pairs every query frame whatever queries says
    text = "\n".join(out) + "\n"
    text = text.replace('name = "autoencoder"', f'name = "{descriptor}"')
    cfg = DATA / f"pairing-s{seed}-{descriptor}-{mode}.toml"
    DATA.mkdir(parents=True, exist_ok=True)
    cfg.write_text(text)
    return cfg


def run_one(world: tuple[str, int, int], descriptor: str, mode: str, out: Path) -> dict:
    """One world, descriptor and mode: the pairs' agreement with the pose pairs."""
    name, seed, frames = world
    cfg = _config(seed, frames, descriptor, mode)
    dst = out / f"s{seed}-{descriptor}-{mode}"
    cmd = [sys.executable, "-m", "harness.cli", "detect", "--config", str(cfg), "--map",
           "2012-01-22", "--query", "2012-03-31", "--query", "2012-08-04", "--query",
           "2012-11-17", "--calibration", "within-run", "--out", str(dst)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    row = {"world": name, "descriptor": descriptor, "mode": mode}
    if proc.returncode != 0:
        return {**row, "error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    rec = json.loads((dst / "detect.json").read_text())
    return {**row, **rec.get("pairing", {}).get("agreement_with_pose_pairs", {})}


def spliced_nordland(dst: Path, splice: bool) -> tuple[Path, Path, dict[str, int | None]] | None:
    """Two folders made from nordland-dev under ``dst``: the map (summer) and the renamed query
    (winter), the map with dark, blank and stopped stretches spliced in where ``splice``.

    Returns the folders and each map file's place (its summer frame's index; None: no place), or
    None where nordland-dev is absent.
    """
    import cv2

    src = REAL / "nordland-dev"
    if not src.is_dir():
        return None
    summer = sorted((src / "summer").glob("*.png"))
    winter = sorted((src / "winter").glob("*.png"))
    mdir, qdir = dst / "map", dst / "query"
    for d in (mdir, qdir):
        d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(3)

    def dark(i: int) -> np.ndarray:
        """A frame of a camera in the dark: a faint smooth glow (mean ~12, sd ~4), little noise."""
        glow = cv2.GaussianBlur(cv2.imread(str(summer[i])).astype(np.float32), (0, 0), 6) * 0.15
        img = 2 + glow + rng.normal(0, 0.5, (32, 64, 3))
        return np.clip(img, 0, 255).astype(np.uint8)

    seq: list[tuple[np.ndarray, int | None]] = []
    if splice:
        seq += [(dark(0), None) for _ in range(17)]  # the camera starting up
    for i, f in enumerate(summer):
        img = cv2.imread(str(f))
        seq.append((img, i))
        if splice and i == 100:
            seq += [(np.zeros_like(img), None), (np.full_like(img, 128), None)]
        if splice and i == 180:
            seq += [(img.copy(), i) for _ in range(19)]  # a stop: 20 frames of one place
    if splice:
        seq += [(dark(len(summer) - 1), None) for _ in range(13)]  # a tunnel
    place = {}
    for k, (img, i) in enumerate(seq):
        name = f"m{k:04d}.png"
        cv2.imwrite(str(mdir / name), img)
        place[name] = i
    for k, f in enumerate(winter):
        (qdir / f"w{k:04d}.png").write_bytes(f.read_bytes())
    return mdir, qdir, place


def nordland_row(out: Path, splice: bool) -> dict | None:
    """``harness detect`` on the (spliced) nordland-dev folders: the share paired right."""
    made = spliced_nordland(DATA / f"nordland-{'spliced' if splice else 'plain'}", splice)
    if made is None:
        print(f"skipped nordland-dev: {REAL / 'nordland-dev'} is not here")
        return None
    mdir, qdir, place = made
    dst = out / f"nordland-{'spliced' if splice else 'plain'}"
    cmd = [sys.executable, "-m", "harness.cli", "detect", "--map-images", str(mdir),
           "--query-images", str(qdir), "--calibration", "within-run",
           "--out", str(dst)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    world = "nordland-dev" + (", dark and stopped stretches spliced in" if splice else "")
    row: dict = {"world": world, "descriptor": "seqslam", "mode": "sequence"}
    if proc.returncode != 0:
        return {**row, "error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    fr = pd.read_csv(dst / "frames.csv")
    got = [place.get(str(r)) for r in fr["r_name"]]
    truth = [int(str(n)[1:5]) for n in fr["name"]]
    right = sum(g is not None and abs(g - t) <= 2 for g, t in zip(got, truth, strict=True))
    rec = json.loads((dst / "detect.json").read_text())
    no_place = rec.get("pairing", {}).get("no_place", {}).get("frames", [])
    return {**row, "agree": right, "compared": len(fr), "share": right / max(len(fr), 1),
            "queries": len(list(qdir.iterdir())), "no_place": len(no_place),
            "hubs": len(rec.get("pairing", {}).get("hubs", []))}  # fmt: skip


def markdown(rows: list[dict]) -> str:
    worlds = [w[0] for w in WORLDS]
    lines = ["| descriptor | mode | " + " | ".join(worlds) + " |",
             "|---|---|" + "---:|" * len(worlds)]  # fmt: skip
    for d in DESCRIPTORS:
        for m in MODES:
            cells = []
            for w in worlds:
                r = next((x for x in rows if (x["world"], x["descriptor"], x["mode"]) == (w, d, m)),
                         None)  # fmt: skip
                if r is None or "agree" not in r:
                    cells.append(f"failed: {r.get('error', '')[:60]}" if r else "-")
                    continue
                lo, hi = 100 * r["share_ci_low"], 100 * r["share_ci_high"]
                cells.append(
                    f"{r['agree']} of {r['compared']} ({100 * r['share']:.0f}%, {lo:.0f}-{hi:.0f}%)"
                )
            lines.append(f"| `{d}` | `{m}` | " + " | ".join(cells) + " |")
    chance = []
    for w in worlds:
        r = next((x for x in rows if x["world"] == w and "chance_share" in x), None)
        chance.append(f"{100 * r['chance_share']:.0f}%" if r else "-")
    lines.append("| a random map frame | | " + " | ".join(chance) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "pairing_truth")
    a = ap.parse_args(argv)
    rows = []
    for w in WORLDS:
        for d in DESCRIPTORS:
            for m in MODES:
                if m == "order" and d != DESCRIPTORS[0]:  # pairs by order read no descriptor
                    first = next(r for r in rows if (r["world"], r["mode"]) == (w[0], "order"))
                    rows.append({**first, "descriptor": d})
                    continue
                rows.append(run_one(w, d, m, a.out))
                print(json.dumps(rows[-1]), flush=True)
    md = markdown(rows)
    real = [r for r in (nordland_row(a.out, False), nordland_row(a.out, True)) if r is not None]
    if real:
        md += (
            "\n| real footage, two folders, no `--config` | paired within 2 frames | frames that "
            "carry no place | hubs |\n|---|---:|---:|---:|\n"
        )
        for r in real:
            cell = (f"{r['agree']} of {r['compared']} ({100 * r['share']:.0f}%)" if "agree" in r
                    else f"failed: {r.get('error', '')[:60]}")  # fmt: skip
            md += f"| {r['world']} | {cell} | {r.get('no_place', '-')} | {r.get('hubs', '-')} |\n"
        rows += real
    write_table(a.out, "pairing_truth", rows, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``python -m bench.pairing_truth [--out DIR]``: how often each pairing descriptor and mode pairs a
new session's frames with the right map frame, where poses give the truth (docs/folders.md).

``harness detect`` as a user types it (``--config``, ``--map``, three ``--query`` sessions), with
``[pairs] by`` set to each mode that needs no poses and ``[descriptor] name`` to each descriptor;
a pair is right within 10 m of the pose pair's map frame (``detect.json``'s
``pairing.agreement_with_pose_pairs``, with its exact 95% interval and the share a random map
frame would reach). Two worlds, made under ``bench/.data/``: the bundled fixture (seed 0, 64
frames a session) and another (seed 7, 128 frames a session); each has four traverses of one
loop, the first the map. Printed as markdown and written to ``OUT/pairing_truth.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from bench.detect_choice import DATA, ROOT, write_table

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
    write_table(a.out, "pairing_truth", rows, markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

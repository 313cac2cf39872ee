"""``python -m bench.alarms [--sets fixture,world,obchange-dev,...] [--out DIR]``: what the alarms
of ``harness detect`` flag where the truth is known, for the no-change null and the old
calibration within the run (docs/decisions.md, *Calibrated alarms*).

Besides the sets of ``python -m bench.detect_choice``, two no-change revisits made from
consecutive frames (``bench.no_change``: ``world-consecutive``, ``nordland-consecutive``): the
camera moved, nothing changed, so every flag is a false alarm.

Each set runs ``harness detect`` as a user types it (the sets of ``python -m bench.detect_choice``,
its default detector), once with ``--calibration null`` and once with ``--calibration within-run``;
from Table D: the share of the frames annotated no-change that the nominal rate 0.01 flags (the
measured false-alarm rate) and of the frames annotated with a change (the detection rate), each
with its exact 95% interval; and the frames and boxes the run flags in all. Printed as markdown
and written to ``OUT/alarms.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd

from bench import no_change
from bench.detect_choice import ROOT, sets_here, write_table

CALIBRATIONS = ("null", "within-run")


def run_one(set_name: str, args: list[str], calibration: str, out: Path) -> dict:
    """One set under one calibration: Table D's alarm columns and the run's alarm counts.

    Both calibrations of a set run into one directory, one after the other: the second reuses
    the first's stages (ingest, proposals, ranks, the detect chunks), only its calibration and
    what follows from it are new, and each run's files are read before the next one writes.
    """
    dst = out / set_name
    cmd = [sys.executable, "-m", "harness.cli", "detect", *args, "--calibration", calibration,
           "--out", str(dst)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    row: dict = {"set": set_name, "calibration": calibration}
    if proc.returncode != 0:
        return {**row, "error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    rec = json.loads((dst / "detect.json").read_text())
    t = pd.read_csv(dst / "tableD.csv").iloc[0]
    row |= {k: rec["alarm"][k] for k in ("rate", "frames", "of_frames", "boxes", "of_boxes")}
    row["null"] = rec["calibration"]
    cols = ("no_change_frames", "alarm_measured", "alarm_ci_low", "alarm_ci_high",
            "changed_frames", "alarm_detected", "detected_ci_low", "detected_ci_high")  # fmt: skip
    for col in cols:
        if col in t.index and t[col] == t[col]:
            row[col] = float(t[col])
    return row


def _rate(r: dict, k: str, lo: str, hi: str, n: str) -> str:
    if k not in r:
        return "-"
    hits = round(r[k] * r[n])
    return f"{hits} of {int(r[n])}: {r[k]:.3f} [{r[lo]:.3f}, {r[hi]:.3f}]"


def markdown(rows: list[dict]) -> str:
    """One row per set and calibration."""
    lines = [
        "| set | calibration | no-change frames flagged at 0.01 [95% exact] | changed frames "
        "flagged at 0.01 [95% exact] | frames flagged | boxes flagged |",
        "|---|---|---|---|---:|---:|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['set']} | {r['calibration']} | failed: {r['error'][:80]} | | | |")
            continue
        null = r["null"]
        how = (
            f"null ({null['pairs']} {null['construction']} pairs)"
            if null.get("method") == "null"
            else "within the run"
        )
        lines.append(
            f"| {r['set']} | {how} | "
            f"{_rate(r, 'alarm_measured', 'alarm_ci_low', 'alarm_ci_high', 'no_change_frames')} | "
            f"{_rate(r, 'alarm_detected', 'detected_ci_low', 'detected_ci_high', 'changed_frames')}"
            f" | {r['frames']} of {r['of_frames']} | {r['boxes']} of {r['of_boxes']} |"
        )
    return "\n".join(lines) + "\n"


def _sets(names: str) -> list[tuple[str, list[str]]]:
    """The sets of ``names`` in order, the no-change ones built from consecutive frames."""
    out = []
    for s in names.split(","):
        if s not in no_change.SETS:
            out += sets_here(s)
        elif (args := no_change.set_args(s)) is not None:
            out.append((s, args))
        else:
            print(f"skipped {s}: its frames are not here (real frames are read from shared/)")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--sets", default="fixture,world,obchange-dev,world-consecutive,nordland-consecutive"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "alarms")
    a = ap.parse_args(argv)
    rows = []
    for s, args in _sets(a.sets):
        for c in CALIBRATIONS:
            rows.append(run_one(s, args, c, a.out))
            print(json.dumps(rows[-1]), flush=True)
    write_table(a.out, "alarms", rows, markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

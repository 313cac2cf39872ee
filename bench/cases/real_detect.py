"""Bench case ``real-detect``: ``harness detect`` end to end, cold, on real robot revisits.

The command as a user types it on ``../shared/realdata/obchange-rooms`` (51 pairs of 640 x 480
photos, 106 annotated change boxes), in a fresh process and a fresh output folder: ingest,
Selective Search's proposals of both folders, keypoint localization, registration and the plain
difference, the no-change null's 100 pairs, Table D and the page. Its stages' times come from
``detect.json``. Beside it, measured in the same run, the kernels' limit: decoding both images of
every pair, SIFT on each image at the two sizes the detector works on, and Selective Search on
each image (the null's query frames are the map's), over the 2 cores (Selective Search's in two
processes). The line: 45 s. Skipped, saying so, where the folder is absent.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

from .common import emit

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT.parent / "shared" / "realdata" / "obchange-rooms"
LINE_S = 45.0


def _kernels() -> float:
    """Seconds of the detector's kernels over the set on 2 cores: decode, SIFT, Selective Search."""
    from harness.detect.config import DetectConfig
    from harness.localizers.keypoints import detect
    from harness.proposals.builtin import selective_boxes
    from harness.proposals.config import SelectiveConfig

    kc = DetectConfig().keypoints
    t0 = time.perf_counter()
    for side in ("A", "B"):
        for f in sorted((REAL / side).glob("*.jpg")):
            rgb = cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)
            g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
            for w in (kc.work_side, 640):
                s = w / max(g.shape)
                detect(cv2.resize(g, None, fx=s, fy=s, interpolation=cv2.INTER_AREA), kc)
            selective_boxes(rgb, SelectiveConfig())
    return (time.perf_counter() - t0) / 2  # two cores


def case_real_detect(quick: bool) -> None:
    if not (REAL / "annotations.csv").is_file():
        print(f"skipped real-detect: {REAL} is not here", file=sys.stderr)
        return
    runs, stages = [], {}
    for _ in range(1 if quick else 3):
        with tempfile.TemporaryDirectory() as d:
            out = Path(d) / "run"
            cmd = [sys.executable, "-m", "harness.cli", "detect", "--map-images", str(REAL / "A"),
                   "--query-images", str(REAL / "B"), "--annotations",
                   str(REAL / "annotations.csv"), "--out", str(out)]  # fmt: skip
            t0 = time.perf_counter()
            subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)
            runs.append(time.perf_counter() - t0)
            rec = json.loads((out / "detect.json").read_text())
            stages = rec["timings_s"]
            ap = rec["table_d"][0]["ap50_voc_all_point"]
    lim = _kernels()
    med = sorted(runs)[len(runs) // 2]
    emit(
        "harness detect on obchange-rooms, cold [51 pairs, annotations, 2 cores]",
        runs,
        "s",
        kernel_limit_s=round(lim, 2),
        ratio_to_kernels=round(med / lim, 2),
        line_s=LINE_S,
        stages_s=stages,
        ap50=ap,
        notes=(
            f"the whole command {med:.1f} s against the line of {LINE_S:.0f} s, {med / lim:.2f}x "
            f"its kernels ({lim:.1f} s: decoding, SIFT at both work sizes and Selective Search "
            f"of every image, over 2 cores); stages {stages}; AP50 {ap:.3f}"
        ),
    )

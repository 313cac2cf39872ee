"""Bench case ``folders``: two folders of images, no shared names, no annotations.

The whole command as a user types it, ``harness detect --map-images MAP --query-images QUERY
--out OUT``, in a fresh process and a fresh output folder: ingest, pairing by sequence with the
training-free descriptor, proposals, keypoint localization, the no-change null, the boxes, the
page. Two sizes, the targets beside them: 200 + 200 frames of 320 x 240 within 60 s, and
600 + 600 frames of 480 x 360 within 180 s, on this machine's cores. Where the time goes is the
run's own ``timings_s`` (``detect.json``), printed with each row.

The frames are made here (``bench/.data/folders-*``, once): a camera sliding along a textured
wall (a random field of coloured blobs), the query session the same walk with a gain, an offset
and a few objects pasted in, its files named differently from the map's so that nothing pairs
by name.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from .common import emit

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "bench" / ".data"

#: (frames a folder, width, height, the target in seconds).
SIZES = ((200, 320, 240, 60.0), (600, 480, 360, 180.0))


def _wall(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A wall ``w`` wide: blobs of colour at several scales, so keypoints and regions exist."""
    img = np.full((h, w, 3), 120, np.uint8)
    for _ in range(w * h // 600):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        r = int(rng.integers(2, max(3, h // 10)))
        cv2.circle(img, (x, y), r, c, -1)
    return cv2.GaussianBlur(img, (0, 0), 0.8)


def folders(n: int, w: int, h: int) -> tuple[Path, Path]:
    """The map and query folders of ``n`` frames of ``w`` x ``h`` (made once under .data)."""
    root = DATA / f"folders-{n}-{w}x{h}"
    a, b = root / "map", root / "query"
    if (root / "done").is_file():
        return a, b
    shutil.rmtree(root, ignore_errors=True)
    a.mkdir(parents=True)
    b.mkdir(parents=True)
    rng = np.random.default_rng(0)
    step = max(2, w // 40)
    wall = _wall(rng, w + step * n, h)
    for i in range(n):
        m = wall[:, i * step : i * step + w]
        q = np.clip(m.astype(np.float32) * 0.9 + 12, 0, 255).astype(np.uint8)
        if i % 5 == 0:  # an object pasted into one query frame in five
            x0, y0 = int(rng.integers(0, w - w // 4)), int(rng.integers(0, h - h // 4))
            c = tuple(int(v) for v in rng.integers(0, 256, 3))
            cv2.rectangle(q, (x0, y0), (x0 + w // 5, y0 + h // 5), c, -1)
        cv2.imwrite(str(a / f"m{i:05d}.jpg"), m[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
        cv2.imwrite(str(b / f"q-{i:05d}.jpg"), q[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
    (root / "done").write_text("")
    return a, b


def _once(a: Path, b: Path, out: Path) -> tuple[float, dict]:
    """One run of the command in a fresh process and folder: (wall seconds, its detect.json)."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "harness.cli", "detect", "--map-images", str(a),
           "--query-images", str(b), "--out", str(out)]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"ERROR: {' '.join(cmd)} failed: {proc.stderr.strip()[-400:]}")
    return wall, json.loads((out / "detect.json").read_text())


def case_folders(quick: bool) -> None:
    for n, w, h, limit in SIZES[:1] if quick else SIZES:
        a, b = folders(n, w, h)
        out = DATA / f"folders-{n}-{w}x{h}-out"
        runs, rec = [], {}
        for _ in range(1 if quick or n > 200 else 3):
            wall, rec = _once(a, b, out)
            runs.append(wall)
        where = ", ".join(f"{k} {v:.1f}" for k, v in sorted(rec["timings_s"].items()))
        emit(
            f"two folders {n}+{n} {w}x{h}",
            runs,
            "s",
            limit=limit,
            within=max(runs) <= limit,
            notes=f"the whole command in a fresh process; target {limit:.0f} s; stages "
            f"s: {where}; null {rec['calibration'].get('pairs')} "
            f"{rec['calibration'].get('construction')} pairs; alarms "
            f"{rec['alarm']['frames']} of {rec['alarm']['of_frames']} frames",
        )

"""No-change revisits made from frames at hand: consecutive frames of one sequence, paired by name.

A real revisit never repeats a view: the camera has moved (parallax, new content at the borders)
even where nothing in the scene changed. Frame ``i`` of a sequence as the map and frame ``i + 1``
as the query, under the same file name, is such a pair with no change at all; every query image is
annotated ``no-change``, so Table D's alarm columns are the measured false-alarm rate of the
nominal one. Two sources:

- ``world-consecutive``: the map session of ``bench.detect_choice``'s held-out generated world
  (240 x 320; a camera driven along a road, about a metre between frames), generated under
  ``bench/.data`` when absent;
- ``nordland-consecutive``: the summer ride of ``../shared/realdata/nordland-dev`` (real, 64 x 32,
  a tenth of the film's frames apart: the train moves several metres between them).

Each set is written once under ``bench/.data/<set>/`` (``A/``, ``B/``, ``annotations.csv``).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2

from bench.detect_choice import DATA, REAL, ROOT, WORLD

SETS = ("world-consecutive", "nordland-consecutive")
#: How many consecutive pairs each set holds (the nominal rate 0.01 flags 0.4 of 40 by chance).
PAIRS = {"world-consecutive": 40, "nordland-consecutive": 100}


def _world_frames() -> list[Path] | None:
    """The generated world's map-session frames in order (generating the world when absent)."""
    seed, frames, w, h, loop = WORLD
    root = DATA / f"world-{w}x{h}-s{seed}"
    cam = root / "nclt" / "images" / "2012-01-22" / "lb3" / "Cam5"
    if not cam.is_dir():
        cmd = [sys.executable, "-m", "harness.cli", "fixture", "--out", str(root), "--seed",
               str(seed), "--frames", str(frames), "--width", str(w), "--height", str(h),
               "--objects", "9", "--loop-scale", str(loop)]  # fmt: skip
        if root.exists():
            cmd.append("--force")
        subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)
    return sorted(cam.glob("*.tiff"), key=lambda p: int(p.stem))


def _nordland_frames() -> list[Path] | None:
    d = REAL / "nordland-dev" / "summer"
    return sorted(d.glob("*.png")) if d.is_dir() else None


def _copy(src: Path, dst: Path) -> None:
    """A PNG as it stands; an NCLT TIFF (stored turned) as the upright PNG its ingest reads."""
    if src.suffix == ".png":
        shutil.copyfile(src, dst)
        return
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"ERROR: {src}: not an image OpenCV reads")
    cv2.imwrite(str(dst), cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE))


def build(name: str) -> Path | None:
    """``bench/.data/<name>/`` with ``A/``, ``B/`` and ``annotations.csv``; None where its source
    is not here (real frames are read from shared/, never kept in the repository)."""
    frames = _world_frames() if name == "world-consecutive" else _nordland_frames()
    if not frames:
        return None
    dst = DATA / name
    n = min(PAIRS[name], len(frames) - 1)
    if (dst / "annotations.csv").is_file():
        return dst
    if dst.exists():  # never replaces a folder it did not finish writing itself
        raise SystemExit(f"ERROR: {dst} exists without its annotations.csv: remove it to rebuild")
    tmp = dst.with_name(dst.name + ".part")  # this module's own unfinished copy
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "A").mkdir(parents=True)
    (tmp / "B").mkdir()
    rows = ["image,status,x1,y1,x2,y2,label"]
    for i in range(n):
        file = f"p{i:03d}.png"
        _copy(frames[i], tmp / "A" / file)
        _copy(frames[i + 1], tmp / "B" / file)
        rows.append(f"{file},no-change,,,,,")
    (tmp / "annotations.csv").write_text("\n".join(rows) + "\n")
    tmp.rename(dst)
    return dst


def set_args(name: str) -> list[str] | None:
    """The ``harness detect`` arguments of a no-change set, or None where it is not here."""
    d = build(name)
    if d is None:
        return None
    return ["--map-images", str(d / "A"), "--query-images", str(d / "B"),
            "--annotations", str(d / "annotations.csv")]  # fmt: skip

"""Ingest one NCLT session: its image folder and ground-truth CSV."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.errors import ConfigError, IngestError
from harness.imagestore import make_uri, stored_size, upright_size
from harness.ingest.config import IngestConfig, SessionConfig
from harness.ingest.frame_table import finish
from harness.ingest.poses import check_monotonic
from harness.inputs import read_text


def read_nclt_groundtruth(
    path: Path, salvage: bool = False, cut: list[int] | None = None
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """NCLT ground truth ``utime, x, y, z, roll, pitch, yaw`` (no header).

    Returns:
        (utime (n,), values (n, 6), number of rows skipped because they hold NaN or infinity,
        1-based line number of each kept row).

    With ``salvage``, a damaged *last* line (a log cut while it was written) is dropped and
    counted in ``cut[0]``; a damaged line anywhere else is still an error.

    Raises:
        IngestError: A row has the wrong number of fields or a non-numeric value (names the line).
    """
    cut = cut if cut is not None else [0]
    text = read_text(path, "ground-truth file", IngestError)
    times, vals, lines, nan_rows = [], [], [], 0
    rows = text.splitlines()
    last = max((i for i, r in enumerate(rows, 1) if r.strip()), default=0)
    for lineno, line in enumerate(rows, 1):
        line = line.strip()
        if not line:
            continue
        parts = line.split(",")
        problem = None
        if len(parts) != 7:
            problem = f"expected 7 fields (utime,x,y,z,roll,pitch,yaw), got {len(parts)}"
        else:
            try:
                t0 = float(parts[0])
                t = int(t0) if math.isfinite(t0) else 0
                v = [float(p) for p in parts[1:]]
            except ValueError:
                problem = f"non-numeric value in {line!r}"
        if problem is not None:
            if salvage and lineno == last:  # a log cut while it was written: keep what precedes
                cut[0] += 1
                continue
            hint = " (the last line: --salvage keeps the rows before it)" if lineno == last else ""
            raise IngestError(f"{path}: line {lineno}: {problem}{hint}")
        if not all(math.isfinite(x) for x in v) or not math.isfinite(t0):
            nan_rows += 1
            continue
        times.append(t)
        vals.append(v)
        lines.append(lineno)
    if not times:
        raise IngestError(f"{path}: no valid ground-truth row")
    t_arr = np.array(times, np.int64)
    line_arr = np.array(lines, np.int64)
    check_monotonic(t_arr, str(path), "ground-truth", numbers=line_arr, unit="line")
    return t_arr, np.array(vals, np.float64), nan_rows, line_arr


def ingest_nclt(sc: SessionConfig, ic: IngestConfig, tmp: Path, report: dict) -> pd.DataFrame:
    """The frame table of one NCLT session: ``images/<session>/lb3/<camera>`` and ground truth."""
    root = Path(sc.source)
    img_dir = root / "images" / sc.name / "lb3" / sc.camera
    if not img_dir.is_dir():
        avail = (
            sorted(p.name for p in (root / "images" / sc.name / "lb3").glob("Cam*"))
            if (root / "images" / sc.name / "lb3").is_dir()
            else []
        )
        raise IngestError(
            f"{img_dir}: no such NCLT image directory (cameras found for {sc.name}: "
            f"{avail or 'none'})"
        )
    gt_path = root / "ground_truth" / f"groundtruth_{sc.name}.csv"
    cut = [0]
    pose_t, pose_v, nan_rows, _ = read_nclt_groundtruth(gt_path, ic.salvage, cut)
    report["dropped"]["groundtruth_non_finite_rows"] = nan_rows
    if cut[0]:
        report["dropped"]["groundtruth_cut_last_line"] = cut[0]
        report["salvaged"] = True
    report["pose_frames"] = {
        "pose_frame": "nclt_world",
        "pose_of": "body",
    }  # NCLT ground truth: the robot body, not the camera
    report["messages_read"] = {"ground_truth_rows": len(pose_t) + nan_rows}
    files = []
    bad = 0
    for p in img_dir.iterdir():
        if p.suffix.lower() not in (".tiff", ".tif", ".png", ".jpg"):
            continue
        try:
            files.append((int(p.stem), p))
        except ValueError:
            bad += 1
    report["dropped"]["bad_image_name"] = bad
    if not files:
        raise IngestError(f"{img_dir}: no images")
    files.sort()  # by utime, then path: of two files with one utime (.png, .tiff) the first is kept
    uniq = [f for i, f in enumerate(files) if i == 0 or f[0] != files[i - 1][0]]
    report["dropped"]["duplicate_image_time"] = len(files) - len(uniq)
    files = uniq
    report["messages_read"]["images"] = len(files)
    rot = ic.nclt_rotation
    sizes, uris = [], []
    for _, p in files:
        w, h = stored_size(p)
        sizes.append(upright_size(w, h, rot))
        uris.append(make_uri(p.resolve(), rot))
    img_t = np.array([t for t, _ in files], np.int64)
    images = (img_t, uris, np.array(sizes, np.int64))
    return finish(sc, ic, tmp, images, (pose_t, pose_v), report)


def inspect_nclt(root: Path) -> dict[str, Any]:
    """What ``harness inspect`` says of an NCLT root: its sessions, cameras, ground-truth rows."""
    out: dict[str, Any] = {"path": str(root), "format": "nclt", "sessions": []}
    for sdir in sorted((root / "images").glob("*")) if (root / "images").is_dir() else []:
        cams = {c.name: sum(1 for _ in c.iterdir()) for c in sorted((sdir / "lb3").glob("Cam*"))}
        gt = root / "ground_truth" / f"groundtruth_{sdir.name}.csv"
        rows = 0
        if gt.exists():  # counted as bytes: a non-UTF-8 byte is the ingest's to name, by line
            rows = sum(1 for line in gt.read_bytes().splitlines() if line.strip())
        out["sessions"].append(
            {
                "session": sdir.name,
                "cameras": cams,
                "ground_truth_rows": rows,
                "ground_truth": str(gt) if gt.exists() else None,
            }
        )
    out["suggested_config"] = "\n".join(
        f'[[sessions]]\nname = "{s["session"]}"\nsource = "{root}"\ncamera = "Cam5"'
        for s in out["sessions"]
    )
    return out


def nclt_sources(sc: SessionConfig) -> dict[str, Path]:
    """The files an NCLT session reads (its key's): its camera's images and its ground truth."""
    src = Path(sc.source)
    return {
        "images": src / "images" / sc.name / "lb3" / sc.camera,
        "gt": src / "ground_truth" / f"groundtruth_{sc.name}.csv",
    }


def check_nclt_camera(sc: SessionConfig) -> None:
    """The session's camera is one of the NCLT root's (before any work).

    Raises:
        ConfigError: naming the cameras found (names are case-sensitive).
    """
    cams = Path(sc.source) / "images" / sc.name / "lb3"
    if not (cams / sc.camera).is_dir():
        found = sorted(d.name for d in cams.glob("*") if d.is_dir()) if cams.is_dir() else []
        raise ConfigError(
            f"sessions {sc.name}: camera = {sc.camera!r}: no {cams / sc.camera}; cameras "
            f"found: {found or 'none'} (names are case-sensitive)"
        )

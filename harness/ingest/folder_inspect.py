"""What ``harness inspect`` says of a folder session (images alone, TUM, KITTI, EuRoC).

The ``inspect`` hook of the folder formats' records (:data:`harness.ingest.logs.READERS`).
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import IngestError
from harness.imagestore import header_size
from harness.ingest.folders import FOLDER_FORMATS, INTEGER_UNITS


def time_span(times: list[int]) -> dict[str, Any]:
    """First and last time (s), span (s) and mean rate (Hz) of log times ``times`` (ns)."""
    if not times:
        return {"first_s": None, "last_s": None, "span_s": 0.0, "rate_hz": 0.0}
    t = np.asarray(times, np.int64)
    span = float(t.max() - t.min()) / 1e9
    return {
        "first_s": float(t.min()) / 1e9,
        "last_s": float(t.max()) / 1e9,
        "span_s": round(span, 3),
        "rate_hz": round((len(t) - 1) / span, 3) if span > 0 else 0.0,
    }


#: How :func:`harness.ingest.folders.stem_to_ns` reads an integer file name, by its factor to ns.
_UNIT_WORDS = {1: "ns", 1_000: "us", 1_000_000: "ms", 1_000_000_000: "s"}


def _name_pattern(stems: list[str]) -> str:
    """How a folder's file names are read as times (method §13.2's folders)."""
    if not stems:
        return "no images"
    if all(s.isdigit() for s in stems):
        units = {_UNIT_WORDS[next(f for lo, f in INTEGER_UNITS if int(s) >= lo)] for s in stems}
        return "integers, times in " + " and ".join(sorted(units))
    try:
        [float(s) for s in stems]
    except ValueError:
        return "names (not times): frames one second apart in name order"
    return "decimal numbers, times in seconds"


def inspect_folder(path: Path, fmt: str) -> dict[str, Any]:
    """Describe a folder session (images alone, or TUM, KITTI, EuRoC) as a dict.

    The images' count, sizes (from their headers, never decoding pixels), how their names read
    as times, whether those times increase in name order, the span and rate, the trajectory's
    poses, and the config lines that would ingest it.

    Raises:
        IngestError: the folder's times or trajectory cannot be read (one line naming the file).
    """
    reader = FOLDER_FORMATS[fmt]
    try:
        frames = reader.images(path)
        poses = reader.poses(path)
    except ValueError as err:
        raise IngestError(str(err)) from None
    sizes: dict[str, int] = {}
    for _, f in frames:
        w, h = header_size(f, str(f))
        sizes[f"{w}x{h}"] = sizes.get(f"{w}x{h}", 0) + 1
    stems = [f.stem for _, f in frames]
    times = [t for t, _ in frames]
    info: dict[str, Any] = {
        "path": str(path),
        "format": fmt,
        "images": len(frames),
        "sizes": sizes,
        "first": frames[0][1].name if frames else None,
        "last": frames[-1][1].name if frames else None,
        "names": _name_pattern(stems),
        "times_file": (path / "times.txt").exists() if fmt == "images" else None,
        "in_order": all(b > a for a, b in itertools.pairwise(times)),
        "poses": len(poses),
        **time_span(times),
    }
    lines = ["[[sessions]]", f'name = "{path.name}"', 'season = ""', f'source = "{path}"']
    if fmt == "images":
        lines.append("# no trajectory: pair it with another folder by retrieval ([pairs] by)")
    info["suggested_config"] = "\n".join(lines)
    return info

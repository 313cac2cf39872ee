"""Ingest one season log into ``frames.parquet`` + ``ingest_report.json`` (+ an image store)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import pandas as pd
import pyarrow as pa

from harness.errors import IngestError
from harness.imagestore import (
    DATA_PREFIX,
    OUT_PREFIX,
    local_uri,
    pixel_limit,
    portable_uri,
    resolve,
)
from harness.ingest.config import IngestConfig, SessionConfig
from harness.ingest.log_session import ingest_log
from harness.ingest.logs import READERS, detect_format, known_formats
from harness.inputs import check_input
from harness.records import FRAME_KEY, FRAME_SCHEMA
from harness.runtime.cache import atomic_dir, write_json, write_parquet
from harness.runtime.outdirs import check_replaceable, write_marker

log = logging.getLogger(__name__)


def ingest_session(sc: SessionConfig, ic: IngestConfig, out: Path, force: bool = False) -> dict:
    """Ingest one session into ``out`` (written atomically; an earlier ``out`` survives a failure).

    ``out`` must be new or empty, or (with ``force``) an earlier ingest output of the harness;
    anything else is refused, never replaced.

    Returns:
        The ingest report (also written to ``out/ingest_report.json``).

    Raises:
        IngestError: Bad input (the message names the file, message or row).
    """
    src = Path(sc.source)
    check_input(src, f"log of session {sc.name}", IngestError, directory=src.is_dir())
    fmt = detect_format(src) if sc.format == "auto" else sc.format
    if fmt not in known_formats():
        raise IngestError(f"{src}: unknown format {fmt!r}; known: {list(known_formats())}")
    out = check_replaceable(Path(out), "ingest", force)
    t0 = time.perf_counter()
    report: dict = {
        "session": sc.name,
        "camera": sc.camera,
        "source": str(src),
        "format": fmt,
        "dropped": {},
    }
    with atomic_dir(Path(out)) as tmp, pixel_limit(ic.max_image_pixels):
        layout = READERS[fmt].ingest  # a layout of its own (nclt), else a stream of messages
        df = (
            layout(sc, ic, tmp, report)
            if layout is not None
            else ingest_log(sc, ic, fmt, tmp, report)
        )
        report["seconds"] = round(time.perf_counter() - t0, 3)
        write_json(tmp / "ingest_report.json", report)
        write_marker(tmp, "ingest", record_entries=True)
    log.info(
        "ingest %s (%s): read %s, wrote %d frames, dropped %s",
        sc.name,
        fmt,
        report.get("messages_read"),
        len(df),
        {k: v for k, v in report["dropped"].items() if v},
    )
    return report


def load_frames(path: Path) -> pd.DataFrame:
    """Read a ``frames.parquet`` and make its image URIs absolute.

    An ingest output's table holds paths relative to itself; a run's frame table
    (``OUT/cache/frames/<key>/frames.parquet``) holds ``{out}/`` and ``{data_root}/`` URIs, resolved
    against the run directory and the data root its ``run.json`` records.

    Raises:
        IngestError: The file is missing, not a frame table, or a run's table whose run
            directory or data root cannot be found.
    """
    path = check_input(path, "frame table", IngestError)
    try:
        df = pd.read_parquet(path)
    except (OSError, ValueError, pa.ArrowException) as err:
        raise IngestError(f"{path}: not a readable parquet frame table ({err})") from None
    miss = [c for c in ("session", "camera", "utime", "image") if c not in df.columns]
    if miss:
        raise IngestError(f"{path}: not a frame table (no column(s) {miss})")
    base = path.parent
    uris = [str(u) for u in df["image"]]
    if any(u.startswith((OUT_PREFIX, DATA_PREFIX)) for u in uris):
        out, root = _run_of(path)
        uris = [local_uri(u, out, root) for u in uris]
    df["image"] = [resolve(u, base) for u in uris]
    return df


def _run_of(path: Path) -> tuple[Path, Path]:
    """The run directory and data root of a run's cached frame table."""
    run = next((d for d in Path(path).resolve().parents if (d / "run.json").is_file()), None)
    if run is None:
        raise IngestError(
            f"{path}: a run's frame table, but no run.json above it names its data root; pass "
            "the frame table of a finished run (OUT/cache/frames/<key>/frames.parquet)"
        )
    try:
        root = json.loads((run / "run.json").read_text())["config"]["data_root"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise IngestError(f"{run / 'run.json'}: unreadable ({err})") from None
    return run, Path(root)


def combine_frames(
    ingest_dirs: list[Path],
    out: Path,
    data_root: Path,
    tmp: Path,
    sources: list[str] | None = None,
) -> dict[str, int]:
    """The frame table of a run: every session's ``frames.parquet``.

    Sorted by session, camera, utime.

    Image URIs are stored relative to ``out`` or ``data_root`` (``{out}/...``, ``{data_root}/...``),
    so a run directory or data root can move.

    Args:
        ingest_dirs: The sessions' ingest entries.
        out: The run directory.
        data_root: The data root of the config.
        tmp: The frames entry's directory (``frames.parquet`` is written there).
        sources: Each session's source now; an ingest entry made before the data root moved
            (its key is the same: keys name sources relative to the data root) names images in
            place under the old source, and those paths are moved along.

    Returns:
        ``{"frames": number of frames}``.
    """
    parts = []
    for i, p in enumerate(ingest_dirs):
        df = load_frames(p / "frames.parquet")
        if sources is not None:
            old = str(json.loads((p / "ingest_report.json").read_text()).get("source", ""))
            new = str(Path(sources[i]).resolve())
            if old and old != new:
                df["image"] = [
                    new + u[len(old) :] if u.startswith(old + "/") else u for u in df["image"]
                ]
        parts.append(df)
    df = pd.concat(parts, ignore_index=True)
    df["image"] = [portable_uri(u, out, data_root) for u in df["image"]]
    write_parquet(tmp / "frames.parquet", df.sort_values(FRAME_KEY), schema=FRAME_SCHEMA)
    return {"frames": len(df)}

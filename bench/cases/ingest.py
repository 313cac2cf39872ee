"""Bench case ``ingest``."""

from __future__ import annotations

import shutil
import statistics
import tempfile
from pathlib import Path

from .common import DATA, emit, read_all, size_of, timed


def case_ingest(quick: bool) -> None:
    """Ingest MB/s of each format next to the raw read speed of the same bytes (warm page cache)."""
    from harness.fixture import FixtureSpec, generate
    from harness.fixture.generate import FORMATS, session_path
    from harness.ingest.config import IngestConfig, SessionConfig

    spec = FixtureSpec(
        frames=16 if quick else 48,
        width=480,
        height=640,
        objects=0,
        sessions=(("2012-01-22", "WI"),),
        changed_sessions=(),
    )
    root = DATA / f"ingest-{spec.frames}"
    if not (root / "fixture.json").exists():
        generate(root, spec, all_formats=True)
    from harness.ingest import ingest_session

    for fmt in FORMATS:
        src = root / session_path(fmt, "2012-01-22")
        nbytes = size_of(src)
        read_all(src)  # warm: the raw read below is from the page cache, an upper bound
        raw = timed(lambda s=src: read_all(s))
        extra = {}
        if fmt != "nclt":
            from harness.ingest.logs import list_topics, stream

            kind = "mcap" if src.suffix == ".mcap" else ("ros1" if src.suffix == ".bag" else "ros2")
            topics = tuple(list_topics(src, kind))
            des = timed(lambda s=src, k=kind, t=topics: [None for _ in stream(s, k, t)])
            extra["deserialize_mb_s"] = round(statistics.median([nbytes / 1e6 / t for t in des]), 1)
        tmp = Path(tempfile.mkdtemp())
        ing = timed(
            lambda s=src, t=tmp: ingest_session(
                SessionConfig(name="2012-01-22", source=str(s)), IngestConfig(), t / "o", force=True
            )
        )
        shutil.rmtree(tmp)
        mb = nbytes / 1e6
        raw_mb_s = statistics.median([mb / t for t in raw])
        emit(
            f"ingest[{fmt}]",
            [mb / t for t in ing],
            "MB/s",
            raw_read_mb_s=round(raw_mb_s, 1),
            **extra,
            notes=f"{mb:.1f} MB, {spec.frames} frames {spec.width}x{spec.height}; ratio to raw "
            f"read {statistics.median([mb / t for t in ing]) / raw_mb_s:.3f}",
        )

"""One session's ingest, the frame table and the annotations' keys.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from harness.ingest.config import IngestConfig, SessionConfig
from harness.ingest.logs import READERS, detect_format
from harness.ingest.masks import folder_digest
from harness.runtime.cache import (
    Parts,
    content_sha,
    file_fingerprint,
    relative_to_root,
    stable_hash,
)


def source_fingerprint(sc: SessionConfig, root: Path | None = None) -> Any:
    """Identity of a session's source: only the files that session reads (paths, sizes, mtimes).

    Paths enter relative to the data root ``root``, so a moved data root keeps every key.
    """
    src = Path(sc.source)
    fmt = detect_format(src) if sc.format == "auto" else sc.format
    rec = READERS.get(fmt)
    if rec is not None and rec.sources is not None:  # a layout: only the files it reads
        return {name: file_fingerprint(path, root) for name, path in rec.sources(sc).items()}
    return file_fingerprint(src, root)


def ingest(ic: IngestConfig, sc: SessionConfig, data_root: Path | None) -> Parts:
    """One session's ingest: its config (source relative to the data root), ``[ingest]``, files."""
    session = {**dataclasses.asdict(sc), "source": relative_to_root(sc.source, data_root)}
    return ("ingest", session, dataclasses.asdict(ic), source_fingerprint(sc, data_root))


def frames(ingest_keys: list[str]) -> Parts:
    """The frame table: the ingest entries it concatenates."""
    return tuple(ingest_keys)


def annotation_file(path: Path) -> str:
    """The annotations a file gives: its content."""
    return content_sha(path)


def masks(folder: Path, min_mask_area: int) -> str:
    """The annotations a mask folder gives: its files' contents and ``[masks] min_mask_area``."""
    return stable_hash("masks", folder_digest(folder), min_mask_area)


def annotation_sources(digests: list[str]) -> str:
    """The annotations of a file and a mask folder together: both their keys."""
    return digests[0] if len(digests) == 1 else stable_hash(*digests)

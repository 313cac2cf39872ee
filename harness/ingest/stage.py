"""The ingest stages (method §3): each session's log, the run's frame table, the annotations.

Each stage function takes the run (:class:`harness.runtime.stage.Units`), its config sections and
the tables before it; its key is made in :mod:`harness.ingest.keys`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from harness.errors import AnnotationError
from harness.imagestore import local_uri
from harness.ingest import keys as ingest_keys
from harness.ingest.annotations import COLUMNS, load_annotations, validate_annotations
from harness.ingest.config import IngestConfig, MasksConfig, SessionConfig
from harness.ingest.masks import read_masks
from harness.ingest.names import frames_by_image, session_names
from harness.ingest.session import combine_frames, ingest_session
from harness.records import FRAME_KEY
from harness.runtime.cache import read_cached_parquet
from harness.runtime.stage import Build, Entry, Table, Units

log = logging.getLogger(__name__)


def ingest_logs(
    p: Units, sessions: Sequence[SessionConfig], ic: IngestConfig, data_root: Path
) -> dict[str, Entry]:
    """Logs -> one ingest entry per session (``frames.parquet``, images, ``ingest_report.json``)."""
    units: list[tuple[tuple[Any, ...], Build]] = [
        (ingest_keys.ingest(ic, sc, data_root), partial(ingest_session, sc, ic)) for sc in sessions
    ]
    return dict(zip([sc.name for sc in sessions], p.units("ingest", units), strict=True))


def frame_table(
    p: Units, ingested: dict[str, Entry], sessions: Sequence[SessionConfig], data_root: Path
) -> Table:
    """Ingest entries -> the run's frame table (image URIs local to this machine)."""
    build = partial(
        combine_frames,
        [e.path for e in ingested.values()],
        p.out,
        data_root,
        sources=[sc.source for sc in sessions],
    )
    entry = p.unit("frames", ingest_keys.frames([e.key for e in ingested.values()]), build)
    df = read_cached_parquet(entry.path / "frames.parquet")
    df["image"] = [local_uri(u, p.out, data_root) for u in df["image"]]
    return Table(df, entry.key)


def annotation_table(
    frames: Table,
    sessions: Sequence[SessionConfig],
    path: Path | None,
    mk: MasksConfig,
    skip: tuple[str, ...] = (),
    optional: bool = False,
) -> Table:
    """The annotations (file ``path``, mask folder ``[masks]`` or both), checked against the frames.

    Rows that name their image (``image``: a folder session's file, method §13.2) and masks
    (``[masks] folder``) get their frame keys from the folder sessions' file names; a frame
    annotated in both is an error. The key is the contents' hash. ``skip``: sessions whose rows
    are not checked (a learned descriptor's training sessions); ``optional``: no annotations is
    fine and only the rows of ``sessions`` are read (``harness detect``).
    """
    parts, digests = [], []
    names = session_names(sessions)
    if path is not None:
        if optional:  # harness detect: the rows of the sessions it reads
            every = load_annotations(path, None, names, skip)
            every = every[every["session"].isin({s.name for s in sessions})]
            every = validate_annotations(every.reset_index(drop=True), frames.df, str(path))
        else:
            every = load_annotations(path, frames.df, names, skip)
        parts.append(every)
        digests.append(ingest_keys.annotation_file(path))
    if mk.folder is not None:
        rows, counts = read_masks(Path(mk.folder), mk.min_mask_area)
        at = [f"mask {n}" for n in rows["image"]]
        parts.append(frames_by_image(rows, names, frames.df, skip, mk.folder, at))
        digests.append(ingest_keys.masks(Path(mk.folder), mk.min_mask_area))
        log.info("masks: %s: %s", mk.folder, counts)
    if not parts:  # harness detect without annotations: no frame is annotated
        return Table(validate_annotations(pd.DataFrame(columns=COLUMNS), None, "none"), "none")
    if len(parts) == 1 and path is not None:
        return Table(parts[0], digests[0])
    both = pd.concat([x[COLUMNS] for x in parts], ignore_index=True)
    if len(parts) == 2:
        twice = set(map(tuple, parts[0][FRAME_KEY].to_numpy())) & set(
            map(tuple, parts[1][FRAME_KEY].to_numpy())
        )
        if twice:
            s, c, u = sorted(twice)[0]
            raise AnnotationError(
                f"{mk.folder}: frame {s} {c} {u} is annotated both in {path} and by a mask"
            )
    where = str(mk.folder) if path is None else f"{path} + {mk.folder}"
    key = ingest_keys.annotation_sources(digests)
    return Table(validate_annotations(both, frames.df, where), key)

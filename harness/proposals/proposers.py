"""Object proposals (qBBs), method §5: the registry of proposers and the stage's driver.

Methods (each one modality with its own retrieval engine):

- ``grid5``: the paper's five fixed boxes (:mod:`harness.proposals.builtin`).
- ``edges``: category-independent proposals from closed edge contours at several scales, scored by
  edge density (in the spirit of EdgeBoxes; no weights needed). The default unsupervised method.
- ``mser``, ``segments``: OpenCV's MSER regions and colour regions (no weights needed).
- ``yolo``: a YOLO-family detector exported to TorchScript, loaded from a local file
  (:mod:`harness.proposals.yolo`).
- ``file``: boxes from a table the user provides (:mod:`harness.proposals.file`).
- any per-image proposer a user adds with :func:`register_proposer`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.errors import ConfigError, HarnessError
from harness.imagestore import read_image
from harness.methods import (
    PROPOSER_OPTIONS,
    PROPOSERS,
    Proposer,
    known_proposal_methods,
)
from harness.proposals import builtin, file, yolo  # noqa: F401  (attach the built-ins' functions)
from harness.proposals.config import ProposalsConfig
from harness.records import FRAME_KEY
from harness.runtime.cache import source_fingerprints, write_parquet
from harness.runtime.progress import progress
from harness.runtime.workers import Workers, shared_workers

log = logging.getLogger(__name__)

PROPOSAL_COLUMNS = [
    "session",
    "camera",
    "utime",
    "proposal_method",
    "box_id",
    "x1",
    "y1",
    "x2",
    "y2",
    "score",
    "class",
]


#: A per-image proposer: the upright (H, W, 3) uint8 RGB image and ``[proposals]`` ->
#: (boxes (k, 4) x1, y1, x2, y2 in pixels, scores (k,), higher = better).
ImageProposer = Callable[[np.ndarray, ProposalsConfig], tuple[np.ndarray, np.ndarray]]


def register_proposer(name: str, proposer: ImageProposer, options: type | None = None) -> None:
    """Add a per-image proposal method, selected by ``name`` in ``[proposals] methods``.

    Its source is part of the proposals' cache key (:func:`proposer_fingerprints`), so editing it
    recomputes them. Each method gets its own rank engine (method §6). ``options``, a
    dataclass, is its ``[proposals.<name>]`` table (unknown keys and wrong types rejected at load,
    part of the proposals' key); the proposer reads it as ``cfg.options_of(name)``. Register
    before the config loads.

    Raises:
        ValueError: ``name`` is taken, or ``options`` is not a dataclass.
    """
    fields = [f.name for f in dataclasses.fields(ProposalsConfig)]  # [proposals]'s own keys
    if name in fields:
        raise ValueError(f"proposal method {name!r} exists: a key of [proposals] itself")
    if options is not None and not dataclasses.is_dataclass(options):
        raise ValueError(f"proposal method {name!r}: options must be a dataclass")
    PROPOSERS.add(name, Proposer(name, "image", run=proposer))
    if options is not None:
        PROPOSER_OPTIONS.add(name, options)


known_methods = known_proposal_methods


def proposer_fingerprints(methods: Sequence[str]) -> dict[str, str]:
    """The source hash of each listed method registered from outside the package."""
    functions = {n: r.run for n, r in PROPOSERS.items() if r.run is not None}
    return source_fingerprints(functions, methods)


def _of(methods: Sequence[str], reads: str) -> list[Proposer]:
    """The listed methods that read ``reads``, in the catalogue's order."""
    return [r for n, r in PROPOSERS.items() if n in methods and r.reads == reads]


def _checked(proposer: str, frame: Any, boxes: Any, scores: Any) -> tuple[np.ndarray, np.ndarray]:
    """A proposer's output as float64 (k, 4) boxes and (k,) scores, or an error naming both.

    Raises:
        ConfigError: The shapes do not match or a value is not finite.
    """
    b, s = np.asarray(boxes, np.float64), np.asarray(scores, np.float64)
    if b.ndim != 2 or b.shape[1] != 4 or s.shape != (len(b),) or not np.isfinite(b).all():
        raise ConfigError(
            f"proposal method {proposer!r} on frame {frame.session}/{frame.camera}/{frame.utime}: "
            f"expected finite boxes (k, 4) and scores (k,), got {b.shape} and {s.shape}"
        )
    return b, s


def _rows(
    f: Any, proposer: str, boxes: np.ndarray, scores: np.ndarray, classes: list[str]
) -> pd.DataFrame:
    """Proposal rows of one frame ``f`` and method (PROPOSAL_COLUMNS)."""
    n = len(boxes)
    return pd.DataFrame(
        {
            "session": f.session,
            "camera": f.camera,
            "utime": np.full(n, f.utime, np.int64),
            "proposal_method": proposer,
            "box_id": np.arange(n, dtype=np.int32),
            "x1": boxes[:, 0] if n else [],
            "y1": boxes[:, 1] if n else [],
            "x2": boxes[:, 2] if n else [],
            "y2": boxes[:, 3] if n else [],
            "score": scores,
            "class": classes,
        }
    )


def _frame_rows(frames: pd.DataFrame, r: Any) -> pd.DataFrame:
    """The rows of a method that reads the frame's size alone (``grid5``), every frame in one table.

    :func:`_rows`' columns, types and values, the frames in order; built once, not a table a frame
    (8.5 ms against 197 ms for 250 NCLT-sized frames, measured).
    """
    sizes = zip(frames["width"], frames["height"], strict=True)
    per = [np.asarray(r.run(w, h), np.float64) for w, h in sizes]
    n = np.array([len(b) for b in per], np.int64)
    boxes = np.concatenate([b.reshape(-1, 4) for b in per]) if n.sum() else np.zeros((0, 4))
    total = int(n.sum())
    return pd.DataFrame(
        {
            "session": np.repeat(frames["session"].to_numpy(object), n),
            "camera": np.repeat(frames["camera"].to_numpy(object), n),
            "utime": np.repeat(frames["utime"].to_numpy(np.int64), n),
            "proposal_method": r.name,
            "box_id": np.concatenate([np.arange(k, dtype=np.int32) for k in n])
            if total
            else np.zeros(0, np.int32),
            **{c: boxes[:, j] for j, c in enumerate(("x1", "y1", "x2", "y2"))},
            "score": np.ones(total),
            "class": [""] * total,
        }
    )


def decode_scale(width: int, cfg: ProposalsConfig, per_image: Sequence[str], batched: bool) -> int:
    """The reduced scale (1, 2, 4 or 8) to decode a frame ``width`` pixels wide (upright) at.

    The largest whose width still holds the widest ``work_width`` of the listed OpenCV methods
    (each works on a copy that wide, so it sees the same detail); 1 where ``reduced_decode`` is
    off, YOLO or ``segments`` is listed (measured: its colour clusters move with the decode's
    noise) or a registered method reads the image (their sizes are their own).
    """
    reducible = [m in PROPOSERS and PROPOSERS[m].reducible for m in per_image]
    if not cfg.reduced_decode or batched or not all(reducible):
        return 1
    need = max((getattr(cfg, m).work_width for m in per_image), default=width)
    return max((k for k in (1, 2, 4, 8) if -(-int(width) // k) >= need), default=1)


def _full_size(boxes: np.ndarray, f: Any, im: np.ndarray) -> np.ndarray:
    """``boxes`` found on ``im`` (a reduced decode of frame ``f``) in the frame's own pixels."""
    h, w = im.shape[:2]
    if (w, h) == (int(f.width), int(f.height)):
        return boxes
    sx, sy = int(f.width) / w, int(f.height) / h
    out = np.round(boxes * np.array([sx, sy, sx, sy]), 2)
    return np.clip(out, 0, [f.width, f.height, f.width, f.height])


def _image_proposals(
    frames: pd.DataFrame,
    cfg: ProposalsConfig,
    methods: list[str],
    progress: Callable[[Iterable], Iterable],
) -> list[pd.DataFrame]:
    """The rows of the methods that read the image, one (OpenCV's, registered) or a batch (YOLO).

    Frame batch by frame batch, each image read once, at the scale :func:`decode_scale` allows.
    """
    out: list[pd.DataFrame] = []
    per_image = [r.name for r in _of(methods, "image")]
    batched = [(r.name, r.run(cfg)) for r in _of(methods, "batch") if r.run is not None]
    if not per_image and not batched:
        return out
    batch = max(1, cfg.yolo.batch)
    items = list(frames.itertuples(index=False))
    threads = cfg.threads if cfg.threads > 0 else len(os.sched_getaffinity(0))
    side_by_side = set(per_image) <= THREADED or len(items) >= 2 * threads  # workers start in ~1 s
    if not batched and threads > 1 and set(per_image) <= THREADED | IN_WORKERS and side_by_side:
        return _threaded_proposals(items, cfg, per_image, threads, progress)
    for i in progress(range(0, len(items), batch)):
        chunk = items[i : i + batch]
        imgs = [
            read_image(f.image, decode_scale(f.width, cfg, per_image, bool(batched))) for f in chunk
        ]
        for m in per_image:
            for f, im in zip(chunk, imgs, strict=True):
                b, s = _one_image(m, f, im, cfg)
                out.append(_rows(f, m, _full_size(b, f, im), s, [""] * len(b)))
        for m, net in batched:
            for f, (b, s, c) in zip(chunk, net(imgs), strict=True):
                out.append(_rows(f, m, b, s, [str(int(k)) for k in c]))
    return out


#: Built-in methods that are functions of the image alone (no process-wide state such as the C
#: library's generator Selective Search draws from), so frames can run side by side in threads.
THREADED = frozenset({"edges", "mser"})
#: Built-in methods whose library call holds process-wide state (Selective Search's ``rand()``):
#: frames run side by side in worker processes (:mod:`harness.runtime.workers`), each seeded per
#: frame, so a frame gives the same boxes whichever process ran it.
IN_WORKERS = frozenset({"selective"})


def start_workers(cfg: ProposalsConfig, methods: Iterable[str]) -> None:
    """Start the worker processes ``methods`` of :data:`IN_WORKERS` run in, ahead of the frames.

    A run that will propose frames calls it first: the workers load their modules while the
    run's own modules load and its sessions are read. The pool is the one the proposals stage
    then uses (:func:`harness.runtime.workers.shared_workers`); nothing starts on one core.
    """
    threads = cfg.threads if cfg.threads > 0 else len(os.sched_getaffinity(0))
    if threads > 1 and set(methods) & IN_WORKERS:
        shared_workers(threads, (builtin.__name__,))


def _threaded_proposals(
    items: list[Any],
    cfg: ProposalsConfig,
    methods: list[str],
    threads: int,
    progress: Callable[[Iterable], Iterable],
) -> list[pd.DataFrame]:
    """:func:`_image_proposals` of methods in :data:`THREADED` and :data:`IN_WORKERS`.

    ``threads`` frames at a time: each frame is read and proposed by one thread (OpenCV and
    libjpeg release the GIL), a method of :data:`IN_WORKERS` in one of ``threads`` worker
    processes; the rows come back in the frames' order, so they are the one-thread rows.
    """
    scale = [decode_scale(f.width, cfg, methods, False) for f in items]
    workers = shared_workers(threads, (builtin.__name__,)) if set(methods) & IN_WORKERS else None

    def one(i: int) -> list[pd.DataFrame]:
        f, im = items[i], read_image(items[i].image, scale[i])
        rows = []
        for m in methods:
            b, s = _one_image(m, f, im, cfg, workers if m in IN_WORKERS else None)
            rows.append(_rows(f, m, _full_size(b, f, im), s, [""] * len(b)))
        return rows

    out: list[pd.DataFrame] = []
    step = 8 * threads
    with ThreadPoolExecutor(threads, thread_name_prefix="proposals") as pool:
        done = pool.map(one, range(len(items)))  # every frame queued: no pause between batches
        for i in progress(range(0, len(items), step)):
            for _ in range(i, min(i + step, len(items))):
                out += next(done)
    return out


def _one_image(
    m: str, f: Any, im: np.ndarray, cfg: ProposalsConfig, workers: Workers | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Method ``m``'s boxes and scores on frame ``f``'s image ``im``, checked.

    ``workers``: where Selective Search runs (:data:`IN_WORKERS`; None: in this process).

    Raises:
        ConfigError: OpenCV refused the method's options, or its output is not boxes and scores.
    """
    run = PROPOSERS[m].run
    if run is None:
        raise ConfigError(f"proposal method {m!r} has no function attached")
    try:
        found = (
            run(im, cfg) if workers is None else builtin.selective_boxes(im, cfg.selective, workers)
        )
    except cv2.error as err:
        raise ConfigError(
            f"proposal method {m!r} on frame {f.session}/{f.camera}/{f.utime}: "
            f"OpenCV refused it ({str(err).strip().splitlines()[-1][:160]}); "
            f"check [proposals.{m}]"
        ) from None
    return _checked(m, f, *found)


def compute_proposals(
    frames: pd.DataFrame,
    cfg: ProposalsConfig,
    progress: Callable[[Iterable], Iterable] = lambda it: it,
) -> pd.DataFrame:
    """Proposal rows (PROPOSAL_COLUMNS) of every method in ``cfg.methods`` for every frame.

    Each method runs as its record says it reads (:class:`harness.methods.Proposer`): the frame's
    size, its image (one or a batch at a time) or a table of the user's.
    """
    frames = frames.sort_values(FRAME_KEY).reset_index(drop=True)
    out: list[pd.DataFrame] = []
    methods = list(cfg.methods)
    unknown = [m for m in methods if m not in known_methods()]
    if unknown:
        raise ConfigError(
            f"[proposals] unknown method(s) {unknown}; known: {list(known_methods())}"
        )
    out += [_frame_rows(frames, r) for r in _of(methods, "frame")]
    out += _image_proposals(frames, cfg, methods, progress)
    out += [r.run(frames, cfg) for r in _of(methods, "table") if r.run is not None]
    out = [d for d in out if len(d)]
    df = pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=PROPOSAL_COLUMNS)
    df["class"] = df["class"].astype(str)
    return (
        df[PROPOSAL_COLUMNS]
        .sort_values(["proposal_method", "session", "camera", "utime", "box_id"])
        .reset_index(drop=True)
    )


def write_proposals(frames: pd.DataFrame, cfg: ProposalsConfig, name: str, tmp: Path) -> dict:
    """One session's proposals (:func:`compute_proposals`) into ``tmp/proposals.parquet``.

    Args:
        frames: The session's frames.
        cfg: ``[proposals]``.
        name: The session (for the progress bar).
        tmp: The entry's directory.

    Returns:
        ``{"rows": proposal rows, "per_method": rows per method}``.
    """
    df = compute_proposals(
        frames, cfg, progress=partial(progress, desc=f"proposals {name}", unit="batch")
    )
    counts = df.groupby("proposal_method").size()
    empty = [m for m in cfg.methods if len(frames) and int(counts.get(m, 0)) == 0]
    if empty:
        raise HarnessError(
            f"proposals ({name}): method {empty[0]!r} gives no box on any of the session's "
            f"{len(frames)} frames, so 'all proposals' would silently mean the other methods "
            f"alone; change [proposals.{empty[0]}] or remove it from [proposals] methods"
        )
    write_parquet(tmp / "proposals.parquet", df)
    return {"rows": len(df), "per_method": df.groupby("proposal_method").size().to_dict()}


#: The earlier name (one vocabulary: a fusion rule, a proposer), kept for plugins.
register_method = register_proposer

"""Object proposals (qBBs), SPEC section 5: the registry of proposers and the stage's driver.

Methods (each one modality with its own retrieval engine):

- ``grid5``: the paper's five fixed boxes (:mod:`harness.proposals.builtin`).
- ``edges``: category-independent proposals from closed edge contours at several scales, scored by
  edge density (in the spirit of EdgeBoxes; no weights needed). The default unsupervised method.
- ``mser``, ``segments``: OpenCV's MSER regions and colour regions (no weights needed).
- ``yolo``: a YOLO-family detector exported to TorchScript, loaded from a local file
  (:mod:`harness.proposals.yolo`).
- ``file``: boxes from a table the user provides (:mod:`harness.proposals.file`).
- any per-image proposer a user adds with :func:`register_method`.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable, Sequence
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
    SPECIAL_PROPOSALS,
    known_proposal_methods,
)
from harness.proposals.builtin import edge_boxes, grid5, mser_boxes, segment_boxes
from harness.proposals.config import ProposalsConfig
from harness.proposals.file import load_file_proposals
from harness.proposals.yolo import YoloProposer
from harness.records import FRAME_KEY
from harness.runtime.cache import source_fingerprints, write_parquet
from harness.runtime.progress import progress

log = logging.getLogger(__name__)

#: Methods with their own code path: grid5 (no pixels), yolo (batched), file (a user's table).
SPECIAL_METHODS = SPECIAL_PROPOSALS
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


# ---------------------------------------------------------------- YOLO (TorchScript)


# ---------------------------------------------------------------- user table


# ---------------------------------------------------------------- driver


#: A per-image proposer: the upright (H, W, 3) uint8 RGB image and ``[proposals]`` ->
#: (boxes (k, 4) x1, y1, x2, y2 in pixels, scores (k,), higher = better).
ImageProposer = Callable[[np.ndarray, ProposalsConfig], tuple[np.ndarray, np.ndarray]]


def _edges(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    return edge_boxes(rgb, cfg.edges)


def _mser(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    return mser_boxes(rgb, cfg.mser)


def _segments(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    return segment_boxes(rgb, cfg.segments)


#: Proposal methods that read one image at a time, by name (``[proposals] methods``): the
#: catalogue's registry (``methods.PROPOSERS``), one dict, holding the built-in ones from here on.
IMAGE_METHODS = PROPOSERS
for _name, _proposer in (("edges", _edges), ("mser", _mser), ("segments", _segments)):
    IMAGE_METHODS.add(_name, _proposer)


def register_method(name: str, proposer: ImageProposer, options: type | None = None) -> None:
    """Add a per-image proposal method, selected by ``name`` in ``[proposals] methods``.

    Its source is part of the proposals' cache key (:func:`method_fingerprints`), so editing it
    recomputes them. Each method gets its own rank engine (SPEC section 6). ``options``, a
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
    IMAGE_METHODS.add(name, proposer)
    if options is not None:
        PROPOSER_OPTIONS.add(name, options)


known_methods = known_proposal_methods


def method_fingerprints(methods: Sequence[str]) -> dict[str, str]:
    """The source hash of each listed method registered from outside the package."""
    return source_fingerprints(IMAGE_METHODS, methods)


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


#: The per-image methods that may read a reduced decode: each works on a copy ``work_width`` wide
#: and gives the same boxes from it (``tests/proposals/test_proposals.py``).
REDUCIBLE = ("edges", "mser")


def decode_scale(width: int, cfg: ProposalsConfig, per_image: Sequence[str], yolo: bool) -> int:
    """The reduced scale (1, 2, 4 or 8) to decode a frame ``width`` pixels wide (upright) at.

    The largest whose width still holds the widest ``work_width`` of the listed OpenCV methods
    (each works on a copy that wide, so it sees the same detail); 1 where ``reduced_decode`` is
    off, YOLO or ``segments`` is listed (measured: its colour clusters move with the decode's
    noise) or a registered method reads the image (their sizes are their own).
    """
    if not cfg.reduced_decode or yolo or any(m not in REDUCIBLE for m in per_image):
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
    """The rows of the methods that read the image: OpenCV's, registered ones, YOLO.

    Frame batch by frame batch, each image read once, at the scale :func:`decode_scale` allows.
    """
    out: list[pd.DataFrame] = []
    per_image = [m for m in IMAGE_METHODS if m in methods]
    if per_image or "yolo" in methods:
        yolo = YoloProposer(cfg.yolo) if "yolo" in methods else None
        batch = max(1, cfg.yolo.batch)
        items = list(frames.itertuples(index=False))
        for i in progress(range(0, len(items), batch)):
            chunk = items[i : i + batch]
            imgs = [
                read_image(f.image, decode_scale(f.width, cfg, per_image, yolo is not None))
                for f in chunk
            ]
            for m in per_image:
                for f, im in zip(chunk, imgs, strict=True):
                    try:
                        found = IMAGE_METHODS[m](im, cfg)
                    except cv2.error as err:
                        raise ConfigError(
                            f"proposal method {m!r} on frame {f.session}/{f.camera}/{f.utime}: "
                            f"OpenCV refused it ({str(err).strip().splitlines()[-1][:160]}); "
                            f"check [proposals.{m}]"
                        ) from None
                    b, s = _checked(m, f, *found)
                    out.append(_rows(f, m, _full_size(b, f, im), s, [""] * len(b)))
            if yolo is not None:
                for f, (b, s, c) in zip(chunk, yolo(imgs), strict=True):
                    out.append(_rows(f, "yolo", b, s, [str(int(k)) for k in c]))
    return out


def _file_proposals(frames: pd.DataFrame, cfg: ProposalsConfig) -> pd.DataFrame:
    """The rows of method ``file``: the user's table, numbered per frame in box order."""
    if not cfg.file:
        raise ConfigError("[proposals] method 'file' needs [proposals] file = <path to the table>")
    fp = load_file_proposals(Path(cfg.file), frames)
    fp = fp.merge(frames[FRAME_KEY], on=FRAME_KEY)
    fp = fp.sort_values(["session", "camera", "utime", "x1", "y1", "x2", "y2"]).reset_index(
        drop=True
    )
    fp["proposal_method"] = "file"
    fp["box_id"] = fp.groupby(FRAME_KEY).cumcount().astype(np.int32)
    return fp[PROPOSAL_COLUMNS]


def compute_proposals(
    frames: pd.DataFrame,
    cfg: ProposalsConfig,
    progress: Callable[[Iterable], Iterable] = lambda it: it,
) -> pd.DataFrame:
    """Proposal rows (PROPOSAL_COLUMNS) of every method in ``cfg.methods`` for every frame."""
    frames = frames.sort_values(FRAME_KEY).reset_index(drop=True)
    out: list[pd.DataFrame] = []
    methods = list(cfg.methods)
    unknown = [m for m in methods if m not in known_methods()]
    if unknown:
        raise ConfigError(
            f"[proposals] unknown method(s) {unknown}; known: {list(known_methods())}"
        )

    if "grid5" in methods:
        for f in frames.itertuples(index=False):
            out.append(_rows(f, "grid5", grid5(f.width, f.height), np.ones(5), [""] * 5))
    out += _image_proposals(frames, cfg, methods, progress)
    if "file" in methods:
        out.append(_file_proposals(frames, cfg))
    df = (
        pd.concat([d for d in out if len(d)], ignore_index=True)
        if out
        else pd.DataFrame(columns=PROPOSAL_COLUMNS)
    )
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

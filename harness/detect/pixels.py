"""The masked frames of ``harness detect``'s pixel AP (``tableD_pixel.csv``).

Each masked query image's sample boxes, their LoC and their plain difference against its mask,
cut into regions; the table itself is :mod:`harness.evaluate.table_d_pixel`'s.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.config.schema import Config
from harness.detect.pair import PairDifference
from harness.errors import AnnotationError
from harness.evaluate.table_d_pixel import MaskedFrame, box_change_fraction, pixel_table
from harness.fusion.fuse import loc_map
from harness.imagestore import read_image
from harness.ingest.names import frames_by_image
from harness.inputs import IMAGE_SUFFIXES
from harness.records import FRAME_KEY, QUERY_KEY
from harness.reports.table_dp import pixel_markdown
from harness.runtime.cache import read_cached_parquet, write_text

log = logging.getLogger(__name__)


def masked_frame(
    boxes: np.ndarray, loc: np.ndarray, mask: np.ndarray, difference: np.ndarray | None = None
) -> MaskedFrame:
    """The regions of one image: its sample boxes and their LoC against its mask.

    ``difference``: each box's aligned-difference contrast, the baseline row that reads the
    pair's pixels and no localizer.
    """
    positive = (mask.max(axis=2) if mask.ndim == 3 else mask) > 0
    h, w = positive.shape
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    own = loc_map(b, np.arange(len(b), dtype=np.float64), w, h)  # each pixel's smallest box
    owner = np.where(np.isfinite(own), own, -1).astype(np.int64)
    codes, area = np.unique((owner + 1) * 2 + positive, return_counts=True)
    return MaskedFrame(
        area.astype(np.float64),
        (codes % 2).astype(bool),
        codes // 2 - 1,
        b,
        np.asarray(loc, np.float64),
        box_change_fraction(b, positive),
        None if difference is None else np.asarray(difference, np.float64),
    )


def mask_frames(
    folder: Path, names: pd.DataFrame, skip_sessions: list[str]
) -> dict[tuple[str, str, int], Path]:
    """Each masked query frame's mask file, by the names :func:`frames_by_image` matches."""
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    rows = pd.DataFrame({"image": [f.name for f in files]})
    keyed = frames_by_image(rows, names, None, skip_sessions, str(folder), [f.name for f in files])
    return {
        (str(s), str(c), int(u)): f
        for (s, c, u), f in zip(
            keyed[["session", "camera", "utime"]].to_numpy(), files, strict=True
        )
    }


def write_pixel_table(
    out: Path,
    cfg: Config,
    names: pd.DataFrame,
    map_session: str,
    entries: list[Any],
    run_frames: pd.DataFrame,
    frames_table: pd.DataFrame,
    opt: Any = None,
) -> pd.DataFrame | None:
    """``tableD_pixel.csv`` / ``.md`` from ``[masks] folder``'s masks of this run's query frames.

    ``run_frames``: the run's frame rows (each query frame's map frame, ``r_*``);
    ``frames_table``: every frame's image, for the plain-difference row; ``opt``: the run's
    ``[detect]`` (the config's where None), whose registration that row uses.

    ``entries`` are the detect chunks (their ``samples.parquet``: boxes and ``loc``), read one at
    a time for the masked frames only; a masked frame without a sample box counts all its pixels
    uncovered. None where no mask names a frame of the run (and an earlier run's table in
    ``out`` is removed).
    """
    files: dict[tuple[str, str, int], Path] = {}
    if cfg.masks.folder is not None:
        ran = set(map(tuple, run_frames[FRAME_KEY].to_numpy().tolist()))
        every = mask_frames(Path(cfg.masks.folder), names, [map_session])
        files = {k: f for k, f in every.items() if k in ran}
        if len(files) < len(every):  # e.g. frames thinned out by [pairs] stride_m
            log.info(
                "pixel AP: %d of %d masks name a frame this run did not detect on, left out",
                len(every) - len(files),
                len(every),
            )
    if not files:  # an earlier run's table into this run directory is not this run's
        for stale in ("tableD_pixel.csv", "tableD_pixel.md"):
            (out / stale).unlink(missing_ok=True)
        return None
    boxes: dict[tuple[str, str, int], tuple[np.ndarray, np.ndarray]] = {}
    images = frames_table.set_index(FRAME_KEY)["image"]
    want = pd.MultiIndex.from_tuples(sorted(files))
    for e in entries:
        s = read_cached_parquet(e.path / "samples.parquet")
        s = s[pd.MultiIndex.from_frame(s[QUERY_KEY]).isin(want)]
        for key, g in s.groupby(QUERY_KEY, sort=True):
            k = (str(key[0]), str(key[1]), int(key[2]))
            boxes[k] = (
                g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64),
                g["loc"].to_numpy(np.float64),
            )
    frames = []
    for k in sorted(files):
        b, loc = boxes.get(k, (np.zeros((0, 4)), np.zeros(0)))
        mask = cv2.imread(str(files[k]), cv2.IMREAD_UNCHANGED)
        if mask is None:  # read as annotations a moment ago: changed on disk since
            raise AnnotationError(f"{files[k]}: not a readable mask image")
        diff = pair_difference(run_frames, images, k, b, opt or cfg.detect)
        frames.append(masked_frame(b, loc, mask, diff))
    r = cfg.report
    t = pixel_table(frames, r.chance_draws, r.bootstrap, r.ci, cfg.seed, r.min_positive_images)
    write_text(out / "tableD_pixel.csv", t.to_csv(index=False, float_format="%.4f"))
    write_text(out / "tableD_pixel.md", pixel_markdown(t))
    return t


def pair_difference(
    run_frames: pd.DataFrame,
    images: pd.Series,
    k: tuple[str, str, int],
    boxes: np.ndarray,
    opt: Any,
) -> np.ndarray | None:
    """Each box's plain-difference contrast in query frame ``k`` against its map frame.

    The pair registered as :mod:`harness.detect.difference` does, with ``opt`` (the run's
    ``[detect]``); NaN where it is not comparable. None where the frame has no map frame (its
    row has no ``r_utime``).
    """
    fk = run_frames.set_index(FRAME_KEY)
    if k not in fk.index or fk.loc[k, "r_utime"] != fk.loc[k, "r_utime"]:
        return None
    r = fk.loc[k]
    m = (str(r["r_session"]), str(r["r_camera"]), int(r["r_utime"]))
    if m not in images.index:
        return None
    q, mm = read_image(str(images.loc[k])), read_image(str(images.loc[m]))
    return PairDifference(q, mm, opt).contrast(boxes)

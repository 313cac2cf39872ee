"""The masked frames of ``harness detect``'s pixel AP (``tableD_pixel.csv``).

Each masked query image's sample boxes, their LoC and their plain difference against its mask,
cut into regions; the table itself is :mod:`harness.evaluate.table_d_pixel`'s.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.detect.pair import PairDifference
from harness.evaluate.table_d_pixel import MaskedFrame, box_change_fraction
from harness.fusion.fuse import loc_map
from harness.imagestore import read_image
from harness.ingest.names import frames_by_image
from harness.inputs import IMAGE_SUFFIXES
from harness.records import FRAME_KEY

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

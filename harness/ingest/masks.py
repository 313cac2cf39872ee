"""Change masks as annotations (method §13.2): one 0/255 image per annotated image, named like it.

A mask folder holds, for each annotated image of a folder session, an image of the same name
(stem; any image suffix) and the same size whose non-zero pixels are change. Its 8-connected
components of at least ``min_mask_area`` pixels become change boxes (``x2``, ``y2`` one past the
last pixel, as annotation boxes are); a mask with none is a ``no-change`` image. The rows name
their image (``image``), as a folder session's annotation CSV may; :func:`harness.ingest.names.
frames_by_image` turns them into frame keys and checks each mask's size against its image.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.errors import AnnotationError
from harness.inputs import IMAGE_SUFFIXES, check_input
from harness.runtime.cache import content_sha, stable_hash

#: The columns of a mask folder's rows: an annotation row by image, and the mask's size.
MASK_COLUMNS = ["image", "status", "x1", "y1", "x2", "y2", "label", "mask_width", "mask_height"]


def mask_boxes(mask: np.ndarray, min_area: int) -> tuple[np.ndarray, int]:
    """The mask's change boxes: its components of ``min_area`` pixels or more.

    Returns (the (n, 4) boxes, how many smaller components were left out); a colour mask counts
    a pixel non-zero in any channel.
    """
    m = mask.max(axis=2) if mask.ndim == 3 else mask
    n, _, stats, _ = cv2.connectedComponentsWithStats((m > 0).astype(np.uint8), connectivity=8)
    st = stats[1:n]
    keep = st[:, cv2.CC_STAT_AREA] >= min_area
    x, y = st[keep, cv2.CC_STAT_LEFT], st[keep, cv2.CC_STAT_TOP]
    w, h = st[keep, cv2.CC_STAT_WIDTH], st[keep, cv2.CC_STAT_HEIGHT]
    boxes = np.stack([x, y, x + w, y + h], axis=1).astype(np.float64).reshape(-1, 4)
    return boxes, int((~keep).sum())


def read_masks(folder: Path, min_area: int) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The annotation rows of a mask folder (:data:`MASK_COLUMNS`) and what was read.

    Raises:
        AnnotationError: not a folder, no mask in it, or a mask that is not a readable image
            (one line naming the file).
    """
    folder = check_input(folder, "mask folder", AnnotationError, directory=True)
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise AnnotationError(
            f"{folder}: no mask image ({', '.join(IMAGE_SUFFIXES)}) in the folder; a mask folder "
            "holds one 0/255 image per annotated image, named like it"
        )
    rows: list[dict[str, Any]] = []
    counts = {"masks": len(files), "no_change": 0, "change_boxes": 0, "small_components": 0}
    for f in files:
        m = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if m is None or m.ndim not in (2, 3):
            raise AnnotationError(f"{f}: not a readable mask image")
        boxes, small = mask_boxes(m, min_area)
        counts["small_components"] += small
        size = {"mask_width": int(m.shape[1]), "mask_height": int(m.shape[0])}
        if not len(boxes):
            counts["no_change"] += 1
            nan = float("nan")
            rows.append({"image": f.name, "status": "no-change", "x1": nan, "y1": nan,
                         "x2": nan, "y2": nan, "label": "", **size})  # fmt: skip
        for x1, y1, x2, y2 in boxes:
            counts["change_boxes"] += 1
            rows.append({"image": f.name, "status": "change", "x1": x1, "y1": y1, "x2": x2,
                         "y2": y2, "label": "mask", **size})  # fmt: skip
    return pd.DataFrame(rows, columns=MASK_COLUMNS), counts


def folder_digest(folder: Path) -> str:
    """A digest of a mask folder's image files: their names and contents."""
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    return stable_hash([(f.name, content_sha(f)) for f in files])

"""The aligned difference: the first thing a change-detection user tries (Table D's row).

A shift-tolerant colour difference of the pair: both frames on a copy whose longer side is
``DIFFERENCE_SIDE`` pixels, in CIELAB, lightly blurred; the map frame's channels matched to the
query's in gain and offset (mean and standard deviation); then, per channel, the distance of each
query pixel to the range the map frame takes within ``shift`` of the frame's diagonal around it
(the minimum over shifts of ``|q(x) - m(x + s)|``, one channel at a time: a grey-scale erosion and
dilation give the range), and the same from the map to the query (a removed object); a pixel's
difference is the larger of the two directions' Euclidean norms over the channels. A box scores
its mean difference less the mean of its ring (:func:`harness.detect.boxes.inside_score`'s
``contrast``): a change differs more than its surroundings.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from harness.detect.boxes import inside_score

#: The longer side of the copies the difference is computed on (pixels), and the largest shift
#: tolerated (a share of the frame's diagonal).
DIFFERENCE_SIDE = 256
DIFFERENCE_SHIFT = 0.03


def _lab(rgb: np.ndarray, side: int) -> np.ndarray:
    h, w = rgb.shape[:2]
    f = min(1.0, side / float(max(h, w)))
    small = (
        rgb
        if f >= 1
        else cv2.resize(
            rgb, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA
        )
    )
    lab = cv2.cvtColor(np.ascontiguousarray(small, np.uint8), cv2.COLOR_RGB2Lab)
    return cv2.GaussianBlur(lab.astype(np.float32), (0, 0), 1.0)


def _one_way(a: np.ndarray, b: np.ndarray, r: int) -> np.ndarray:
    """Per pixel of ``a``: the norm over channels of its distance to ``b``'s range within ``r``."""
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    lo = cv2.erode(b, k, borderType=cv2.BORDER_REPLICATE)
    hi = cv2.dilate(b, k, borderType=cv2.BORDER_REPLICATE)
    d = np.maximum(np.maximum(lo - a, a - hi), 0.0)
    return np.sqrt((d * d).sum(axis=2))


def difference_map(
    q_rgb: np.ndarray, m_rgb: np.ndarray, side: int = DIFFERENCE_SIDE,
    shift: float = DIFFERENCE_SHIFT,
) -> tuple[np.ndarray, float]:  # fmt: skip
    """The pair's shift-tolerant difference on the query's copy, and that copy's scale."""
    q = _lab(q_rgb, side)
    m = _lab(m_rgb, side)
    if m.shape != q.shape:
        m = cv2.resize(m, (q.shape[1], q.shape[0]), interpolation=cv2.INTER_AREA)
    qm, qs = q.reshape(-1, 3).mean(0), q.reshape(-1, 3).std(0) + 1e-6
    mm, ms = m.reshape(-1, 3).mean(0), m.reshape(-1, 3).std(0) + 1e-6
    m = ((m - mm) / ms * qs + qm).astype(np.float32)
    r = max(1, round(shift * float(np.hypot(*q.shape[:2]))))
    d = np.maximum(_one_way(q, m, r), _one_way(m, q, r))
    return d.astype(np.float32), q.shape[1] / float(q_rgb.shape[1])


def difference_contrast(dmap: np.ndarray, scale: float, boxes: np.ndarray) -> np.ndarray:
    """Each box's (frame pixels) mean difference less its ring's, on ``dmap`` (its ``scale``)."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4) * scale
    return np.array([inside_score(dmap, x, "contrast") for x in b], np.float64)


#: Table D's baseline that reads the pair's pixels but no localizer: the candidates scored by the
#: aligned difference's contrast. The detector is above only when it clears this row too.
PIXEL_BASELINES = ("aligned_difference",)


def difference_dets(
    by_image: dict[int, tuple[np.ndarray, np.ndarray]], nms: Any
) -> dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """The aligned-difference row: per image id, the (boxes, scores) the detector's NMS keeps.

    The candidates scored by their difference; none where no candidate carries one.
    """
    if not any(np.isfinite(sc).any() for _, sc in by_image.values()):
        return {}
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for i, (boxes, sc) in by_image.items():
        sc = np.where(np.isfinite(sc), sc, -np.inf)
        keep = np.asarray(nms(boxes, sc), np.int64)
        out[i] = (boxes[keep], sc[keep])
    return {"aligned_difference": out}

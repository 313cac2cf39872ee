"""``harness detect``'s candidate boxes (method §13.1, 13.3): generators, NMS, area prior."""

from __future__ import annotations

import logging

import cv2
import numpy as np

from harness.detect.config import BOX_GENERATORS
from harness.errors import ConfigError
from harness.fusion.fuse import loc_map

log = logging.getLogger(__name__)


def _pixels(m: np.ndarray, box: np.ndarray) -> tuple[int, int, int, int]:
    """The pixel rows and columns (v0, v1, u0, u1) whose centres lie in ``box``."""
    h, w = m.shape
    x1, y1, x2, y2 = box
    u0, u1 = max(int(np.ceil(x1 - 0.5)), 0), min(int(np.ceil(x2 - 0.5)), w)
    v0, v1 = max(int(np.ceil(y1 - 0.5)), 0), min(int(np.ceil(y2 - 0.5)), h)
    return v0, v1, u0, u1


def inside_score(m: np.ndarray, box: np.ndarray, how: str) -> float:
    """A box's score from the LoC map ``m`` (NaN: no mapped pixel centred in it).

    ``max`` or ``mean`` over the pixels centred in ``box``; ``contrast``: their mean less the mean
    of the mapped pixels of the ring around it (the box grown by half its width and height on each
    side, clipped to the frame), or less 0 where the ring holds none: a change is hotter than its
    surroundings, and a box that merely overlaps a hot region scores less than one that frames it.
    """
    v0, v1, u0, u1 = _pixels(m, box)
    part = m[v0:v1, u0:u1]
    if not part.size or not np.isfinite(part).any():
        return float("nan")
    if how == "max":
        return float(np.nanmax(part))
    inner = float(np.nanmean(part))
    if how == "mean":
        return inner
    x1, y1, x2, y2 = box
    gw, gh = (x2 - x1) / 2, (y2 - y1) / 2
    r0, r1, c0, c1 = _pixels(m, np.array([x1 - gw, y1 - gh, x2 + gw, y2 + gh]))
    ring = m[r0:r1, c0:c1].copy()
    ring[v0 - r0 : v1 - r0, u0 - c0 : u1 - c0] = np.nan
    return inner - (float(np.nanmean(ring)) if np.isfinite(ring).any() else 0.0)


def candidate_boxes(
    generator: str,
    fused: np.ndarray,
    loc: np.ndarray,
    originals: np.ndarray,
    width: int,
    height: int,
    how: str = "max",
    level: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """A frame's candidate change boxes and their scores under a box generator (method §13.1).

    ``fused``: the fused qBBs and their LoC. ``proposals`` and ``segments``: the boxes
    ``originals`` (the frame's original proposals, or its colour regions), duplicates merged, each
    scored by the ``how`` (:func:`inside_score`) of the pixel-wise LoC map. ``locmap``: the LoC map
    thresholded at ``lo + level * (hi - lo)`` of the frame's range, the bounding boxes of its
    8-connected regions (``cv2.connectedComponentsWithStats``), each scored by the ``how`` of the
    LoC over the region's own pixels (``contrast``: over its box, as :func:`inside_score`).

    Returns:
        (boxes (k, 4) in pixels, scores (k,), NaN where a box holds no mapped pixel).
    """
    fused = np.asarray(fused, np.float64).reshape(-1, 4)
    loc = np.asarray(loc, np.float64)
    if generator == "fused":
        return fused, loc
    m = loc_map(fused, loc, width, height)
    if generator in ("proposals", "segments"):
        boxes = np.unique(np.asarray(originals, np.float64).reshape(-1, 4), axis=0)
        return boxes, np.array([inside_score(m, b, how) for b in boxes], np.float64)
    if generator != "locmap":
        raise ConfigError(f"[detect] boxes = {generator!r}: one of {', '.join(BOX_GENERATORS)}")
    ok = np.isfinite(m)
    if not ok.any():
        return np.zeros((0, 4)), np.zeros(0)
    lo, hi = float(m[ok].min()), float(m[ok].max())
    mask = (ok & (m >= lo + level * (hi - lo))).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    found: list[tuple[int, int, int, int]] = []
    scores: list[float] = []
    for i in range(1, n):
        x, y, w, h = (int(v) for v in stats[i, :4])
        vals = m[labels == i]
        found.append((x, y, x + w, y + h))
        if how == "contrast":
            scores.append(inside_score(m, np.array(found[-1], np.float64), how))
        else:
            scores.append(float(vals.max() if how == "max" else vals.mean()))
    return np.asarray(found, np.float64).reshape(-1, 4), np.asarray(scores, np.float64)


def with_prior(score: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Scores fused with a prior by the mean of their within-frame percentiles.

    ``[detect] box_prior = "difference"``: the prior is the aligned difference's contrast. A box
    without a finite score keeps none, a box without a finite prior value takes its lowest
    percentile.
    """
    from scipy.stats import rankdata  # scipy.stats costs half a second: only where a prior asks

    out = np.full(len(score), np.nan)
    ok = np.isfinite(score)
    n = int(ok.sum())
    if n:
        pr = np.where(np.isfinite(prior[ok]), prior[ok], -np.inf)
        out[ok] = ((rankdata(score[ok]) - 0.5) / n + (rankdata(pr) - 0.5) / n) / 2
    return out


def with_area_prior(boxes: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Scores fused with box area (``[detect] box_prior = "area"``, method §13.3).

    Each box's score becomes the mean of its percentile among the frame's scored boxes by
    ``score`` and by area (``(rank - 0.5) / n``, ties sharing their mean rank); a box without a
    finite score keeps none. Within-frame percentiles put every frame on one scale, so the
    pooled ranking does not follow whichever frames happen to score high overall; the area
    part is the prior a no-pixel baseline reads, so Table D's paired test against box area
    alone measures what the pixels add.
    """
    from scipy.stats import rankdata  # scipy.stats costs half a second: only where a prior asks

    out = np.full(len(score), np.nan)
    ok = np.isfinite(score)
    n = int(ok.sum())
    if n:
        b = boxes[ok]
        area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
        out[ok] = ((rankdata(score[ok]) - 0.5) / n + (rankdata(area) - 0.5) / n) / 2
    return out

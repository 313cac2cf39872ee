"""The colours' novelty: how much likelier a new pixel's colour is in the new frame than in the map.

docs/decisions.md, *The colours' novelty*. A pair that cannot be registered still says which
colours the new frame holds that its map frame does not: an object put on a desk brings colours
the desk's first view lacks, wherever the robot stood. Each pixel of the new frame scores the log
ratio of its colour's share of the new frame to that colour's share of the map frame (CIELAB
histograms of ``colour_bins`` bins, smoothed by one bin so that a colour a little off its bin is
not new), floored at 0 and blurred like the difference; a box scores that map as it scores the
difference (:func:`harness.detect.difference.difference_contrast`). No keypoint and no warp take
part, so it reads the same on a registered pair and on one that is not.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from harness.detect.config import DifferenceConfig

#: a colour no pixel holds has this share (keeps the log ratio finite)
_EPS = 1e-4


def _lab_bins(rgb: np.ndarray, side: int, bins: tuple[int, int, int]) -> tuple[np.ndarray, float]:
    """Each pixel's colour bin on a copy at most ``side`` long, and that copy's scale."""
    h, w = rgb.shape[:2]
    f = min(1.0, side / max(h, w))
    small: np.ndarray = np.ascontiguousarray(rgb, np.uint8)
    if f < 1:
        size = (max(1, round(w * f)), max(1, round(h * f)))
        small = cv2.resize(small, size, interpolation=cv2.INTER_AREA)
    lab = cv2.cvtColor(small, cv2.COLOR_RGB2Lab).astype(np.int64)
    b = [(lab[..., c] * bins[c]) // 256 for c in range(3)]
    return (b[0] * bins[1] + b[1]) * bins[2] + b[2], f


def _shares(idx: np.ndarray, bins: tuple[int, int, int]) -> np.ndarray:
    """The smoothed share of each colour bin among ``idx``'s pixels."""
    hist = np.bincount(idx.ravel(), minlength=int(np.prod(bins))).reshape(bins)
    smooth = gaussian_filter(hist.astype(np.float64), 1.0, mode="constant")
    return smooth / max(float(smooth.sum()), 1e-12)


def colour_novelty(
    q_rgb: np.ndarray, m_rgb: np.ndarray, dc: DifferenceConfig
) -> tuple[np.ndarray, float]:
    """The new frame's colour novelty against its map frame, on a copy; and that copy's scale."""
    bins = tuple(int(b) for b in dc.colour_bins)
    qi, f = _lab_bins(q_rgb, dc.colour_side, bins)  # type: ignore[arg-type]
    mi, _ = _lab_bins(m_rgb, dc.colour_side, bins)  # type: ignore[arg-type]
    ratio = np.log((_shares(qi, bins) + _EPS) / (_shares(mi, bins) + _EPS))  # type: ignore[arg-type]
    out = np.maximum(ratio.ravel()[qi], 0.0).astype(np.float32)
    sigma = dc.blur * float(np.hypot(*out.shape))
    if sigma > 0:
        out = cv2.GaussianBlur(out, (0, 0), sigma)
    return out, f

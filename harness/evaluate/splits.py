"""RoC/SoB difficulty labels (method §8)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from harness.evaluate.config import SplitsConfig

POSITIVE, NEGATIVE, LEFT_OUT = 1, 0, -1


def _union_area_in(box: np.ndarray, rects: np.ndarray) -> float:
    """Exact area of ``box`` intersected with the union of ``rects`` (coordinate compression)."""
    x1 = np.maximum(rects[:, 0], box[0])
    y1 = np.maximum(rects[:, 1], box[1])
    x2 = np.minimum(rects[:, 2], box[2])
    y2 = np.minimum(rects[:, 3], box[3])
    keep = (x2 > x1) & (y2 > y1)
    if not keep.any():
        return 0.0
    x1, y1, x2, y2 = x1[keep], y1[keep], x2[keep], y2[keep]
    if len(x1) == 1:
        return float((x2[0] - x1[0]) * (y2[0] - y1[0]))
    xs = np.unique(np.concatenate([x1, x2]))
    ys = np.unique(np.concatenate([y1, y2]))
    cx0, cx1 = xs[:-1], xs[1:]
    cy0, cy1 = ys[:-1], ys[1:]
    # cell (i, j) is covered if some rect contains it
    inx = (x1[:, None] <= cx0[None, :]) & (x2[:, None] >= cx1[None, :])  # (r, nx)
    iny = (y1[:, None] <= cy0[None, :]) & (y2[:, None] >= cy1[None, :])  # (r, ny)
    covered = np.einsum("rx,ry->xy", inx.astype(np.int32), iny.astype(np.int32)) > 0
    area = np.outer(cx1 - cx0, cy1 - cy0)
    return float(area[covered].sum())


def roc_sob(
    boxes: np.ndarray, change_boxes: np.ndarray, width: float, height: float
) -> tuple[np.ndarray, np.ndarray]:
    """RoC and SoB of sample boxes.

    ``RoC(b) = area(b ∩ U) / area(b)`` with U the union of the change boxes (overlaps counted
    once), ``SoB(b) = area(b) / (width * height)``.

    Args:
        boxes: (m, 4) x1, y1, x2, y2 with positive area.
        change_boxes: (c, 4); c = 0 for a no-change frame.
        width: the image width, pixels.
        height: the image height, pixels.

    Returns:
        (roc (m,), sob (m,)) float arrays.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    change = np.asarray(change_boxes, np.float64).reshape(-1, 4)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    if np.any(area <= 0):
        raise ValueError("sample boxes must have positive area")
    sob = area / float(width * height)
    if len(change) == 0:
        return np.zeros(len(boxes)), sob
    inter = np.array([_union_area_in(b, change) for b in boxes])
    return np.clip(inter / area, 0.0, 1.0), sob


@dataclass(frozen=True)
class Split:
    """A named set of RoC/SoB ranges (closed intervals)."""

    name: str
    pos_roc: tuple[float, float]
    pos_sob: tuple[float, float]
    neg_roc: tuple[float, float]
    neg_sob: tuple[float, float]

    @property
    def roc_max(self) -> float:
        """The split's RoC-max: the upper end of the negatives' RoC range."""
        return self.neg_roc[1]


def _pair(bounds: Sequence[float]) -> tuple[float, float]:
    """A config range ``[lo, hi]`` as a (lo, hi) tuple."""
    lo, hi = bounds
    return float(lo), float(hi)


def paper_splits(cfg: SplitsConfig | None = None) -> list[Split]:
    """The paper's splits: one per ``RoC-max`` (Table I's columns) with the default ranges."""
    cfg = cfg or SplitsConfig()
    return [
        Split(
            f"roc_max_{r:.2f}",
            _pair(cfg.pos_roc),
            _pair(cfg.pos_sob),
            (cfg.neg_roc_min, float(r)),
            _pair(cfg.neg_sob),
        )
        for r in cfg.roc_max
    ]


def _within(v: np.ndarray, rng: tuple[float, float]) -> np.ndarray:
    return (v >= rng[0]) & (v <= rng[1])


def label(roc: np.ndarray, sob: np.ndarray, split: Split) -> np.ndarray:
    """+1 positive, 0 negative, -1 left out.

    A sample in both ranges (only with custom, overlapping ranges) counts as positive.
    """
    pos = _within(roc, split.pos_roc) & _within(sob, split.pos_sob)
    neg = _within(roc, split.neg_roc) & _within(sob, split.neg_sob)
    out = np.full(len(roc), LEFT_OUT, np.int8)
    out[neg] = NEGATIVE
    out[pos] = POSITIVE
    return out

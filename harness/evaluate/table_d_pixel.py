"""Table D's pixel AP (``tableD_pixel.csv``): LoC maps against change masks (method §9 and 13.2).

Where annotations come as a mask folder, the masks themselves are the truth of a pixel AP: each
pixel of a masked query image takes the LoC of the smallest sample box holding it (the LoC map
the page shows; a pixel no box covers takes the lowest LoC of the run), a pixel is positive where
its mask is non-zero, and the pixels of every masked image are pooled into one 101-point AP.

Pixels of one image that share their owning box and their label form one region weighted by its
pixel count (:class:`MaskedFrame`, cut by :func:`harness.detect.pixels.masked_frame`), so every
figure costs a sort of regions, not of pixels. method §9's floor and chance band: the same boxes
scored at random through the same maps; its ceiling: every box scored by its change fraction
under the mask (its RoC). The baselines that read no pixel (method §13.3) score each box by its
area and by its cover count through the same maps; the detector's verdict is method §9's rule,
and ``above`` only when it is also clear of the best of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pandas as pd

from harness.evaluate import chance
from harness.evaluate.metrics import (
    bootstrap_aps,
    interval,
    resample_counts,
    weighted_average_precision,
)
from harness.evaluate.pixel_aps import region_scores
from harness.evaluate.table_d import no_pixel_scores
from harness.evaluate.table_d_chance import NO_PIXEL, PIXEL_BASELINES

#: The rows of the pixel table: the detector's LoC map, one random scoring of the same boxes
#: (the paired test's reference) and the no-pixel baselines.
PIXEL_ROWS = {
    "detector": "detector (LoC map)",
    "random": "random (random box scores)",
    "size_prior": "size_prior (box area, no pixel read)",
    "cover_count": "cover_count (boxes overlapping it, no pixel read)",
    "difference_same_boxes": "plain difference, registered (box contrast, pixels, no localizer)",
}


@dataclass(frozen=True)
class MaskedFrame:
    """One masked query image cut into regions: pixels that share an owning box and a label.

    ``owner`` is the index of the smallest of ``boxes`` holding the region (-1: no box covers
    it); ``roc`` each box's share of change pixels (the ceiling's scores).
    """

    area: np.ndarray
    positive: np.ndarray
    owner: np.ndarray
    boxes: np.ndarray
    loc: np.ndarray
    roc: np.ndarray
    # each box's aligned-difference contrast (harness.detect.difference; None: no pair image)
    difference: np.ndarray | None = None


def box_change_fraction(boxes: np.ndarray, positive: np.ndarray) -> np.ndarray:
    """Each box's share of positive pixels, a pixel inside when its centre is (as in the maps)."""
    h, w = positive.shape
    ii = cv2.integral(positive.astype(np.uint8)).astype(np.float64)
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    u0 = np.clip(np.ceil(b[:, 0] - 0.5), 0, w).astype(np.int64)
    u1 = np.clip(np.ceil(b[:, 2] - 0.5), 0, w).astype(np.int64)
    v0 = np.clip(np.ceil(b[:, 1] - 0.5), 0, h).astype(np.int64)
    v1 = np.clip(np.ceil(b[:, 3] - 0.5), 0, h).astype(np.int64)
    inside = ii[v1, u1] - ii[v0, u1] - ii[v1, u0] + ii[v0, u0]
    n = (u1 - u0).clip(0) * (v1 - v0).clip(0)
    return np.divide(inside, n, out=np.zeros(len(b)), where=n > 0)


class _Regions:
    """Every masked frame's regions laid end to end, scored through their owning boxes."""

    def __init__(self, frames: list[MaskedFrame]) -> None:
        self.y = np.concatenate([f.positive for f in frames]) if frames else np.zeros(0, bool)
        self.w = np.concatenate([f.area for f in frames]) if frames else np.zeros(0)
        self.g = np.concatenate(
            [np.full(len(f.area), i) for i, f in enumerate(frames)] or [np.zeros(0, np.int64)]
        )
        starts = np.cumsum([0] + [len(f.boxes) for f in frames])
        self.unit = np.concatenate(
            [np.where(f.owner >= 0, f.owner + starts[i], -1) for i, f in enumerate(frames)]
            or [np.zeros(0, np.int64)]
        )
        self.n = int(starts[-1])
        self.boxes = np.concatenate([f.boxes for f in frames]) if frames else np.zeros((0, 4))
        self.scores = {
            "detector": np.concatenate([f.loc for f in frames]) if frames else np.zeros(0),
            "ceiling": np.concatenate([f.roc for f in frames]) if frames else np.zeros(0),
        }
        for name in NO_PIXEL:
            self.scores[name] = np.concatenate(
                [no_pixel_scores(f.boxes)[name] for f in frames] or [np.zeros(0)]
            )
        if frames and all(f.difference is not None for f in frames):
            self.scores[PIXEL_BASELINES[1]] = np.concatenate([f.difference for f in frames])
        self.positive_images = len({int(g) for g in self.g[self.y & (self.w > 0)]})

    def region_scores(self, s: np.ndarray) -> np.ndarray:
        """(b, regions) scores of (b, units) box scores; uncovered regions the row's lowest."""
        return region_scores(s, self.unit)  # a box without a LoC (unaligned) scores as no box

    def aps(self, s: np.ndarray) -> np.ndarray:
        """Pixel AP of each row of (b, units) box scores."""
        return chance.aps_of_rows(self.y, self.region_scores(s), self.w)


def pixel_table(
    frames: list[MaskedFrame],
    draws: int,
    n_boot: int,
    ci: float,
    seed: int,
    needed: int = chance.MIN_POSITIVE_IMAGES,
) -> pd.DataFrame:
    """The pixel AP rows (:data:`PIXEL_ROWS`) with method §9's floor, band, ceiling and verdicts.

    Args:
        frames: the masked query images.
        draws: random scorings of the boxes for the floor and band.
        n_boot: bootstrap resamples of the masked images for the intervals.
        ci: interval level.
        seed: seeds the draws, the random row and the resamples.
        needed: ``[report] min_positive_images`` (method §9, evidence before a verdict).
    """
    r = _Regions(frames)
    k = (r.n, len(frames))
    floor, lo, hi = chance.summarise(
        chance.random_draws(r.aps, r.n, draws, chance.draw_seed(seed, "DP", *k))
    )
    ceiling = float(r.aps(r.scores["ceiling"])[0]) if r.n else float("nan")
    r.scores["random"] = np.random.default_rng(chance.draw_seed(seed, "DP-random", *k)).random(r.n)
    counts = resample_counts(len(frames), n_boot, chance.draw_seed(seed, "DP-boot", len(frames)))
    ap, boot = {}, {}
    here = {k: v for k, v in PIXEL_ROWS.items() if k in r.scores}
    for row in here:
        s = r.region_scores(r.scores[row])[0]
        ap[row] = weighted_average_precision(r.y, s, r.w)
        boot[row] = bootstrap_aps(r.y, s, r.g, counts, weights=r.w)
    # the detector must clear the best row that reads no pixel, or reads pixels but no localizer
    best = max((b for b in (*NO_PIXEL, *PIXEL_BASELINES) if b in here), key=lambda b: (ap[b], b))
    total = float(r.w.sum())
    rows = []
    for row, label in here.items():
        bl, bh = interval(boot[row], ci)
        dl, dh = interval(boot[row] - boot["random"], ci)
        v = chance.verdict(ap[row], lo, hi, dl, dh, chance.Evidence(r.positive_images, needed))
        nl, nh = interval(boot[row] - boot[best], ci) if row == "detector" else (np.nan, np.nan)
        rows.append(
            {
                "row": label,
                "pixel_ap": ap[row],
                "ci_low": bl,
                "ci_high": bh,
                "floor": floor,
                "chance_low": lo,
                "chance_high": hi,
                "ceiling": ceiling,
                "gap_closed": chance.gap_closed(ap[row], floor, ceiling),
                "vs_random_ci_low": dl,
                "vs_random_ci_high": dh,
                "verdict": chance.versus_no_pixel(v, nl) if row == "detector" else v,
                "positive_rate": float(r.w[r.y].sum()) / total if total else np.nan,
                "masked_frames": len(frames),
                "positive_images": r.positive_images,
                "positive_images_needed": needed,
                "best_no_pixel": best if row == "detector" else "",
                "vs_no_pixel_ci_low": nl,
                "vs_no_pixel_ci_high": nh,
            }
        )
    return pd.DataFrame(rows)

"""Pixel AP of ``harness detect``'s LoC maps against change masks (method §9 and 13.2).

Where annotations come as a mask folder, the masks themselves are the truth of a pixel AP: each
pixel of a masked query image takes the LoC of the smallest sample box holding it (the LoC map
the page shows; a pixel no box covers takes the lowest LoC of the run), a pixel is positive where
its mask is non-zero, and the pixels of every masked image are pooled into one 101-point AP.

Pixels of one image that share their owning box and their label form one region weighted by its
pixel count, so every figure costs a sort of regions, not of pixels. method §9's floor and chance
band: the same boxes scored at random through the same maps; its ceiling: every box scored by its
change fraction under the mask (its RoC). The baselines that read no pixel (method §13.3) score each
box by its area and by its cover count through the same maps; the detector's verdict is method §9's
rule, and ``above`` only when it is also clear of the best of them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.config.schema import Config
from harness.detect.difference import (
    box_differences,
    difference_map,
    novelty_of,
    register,
)
from harness.errors import AnnotationError
from harness.evaluate import chance
from harness.evaluate.metrics import (
    bootstrap_aps,
    interval,
    resample_counts,
    weighted_average_precision,
)
from harness.evaluate.table_d import no_pixel_scores
from harness.evaluate.table_d_chance import NO_PIXEL, PIXEL_BASELINES
from harness.fusion.fuse import loc_map
from harness.imagestore import read_image
from harness.ingest.names import frames_by_image
from harness.inputs import IMAGE_SUFFIXES
from harness.records import FRAME_KEY, QUERY_KEY
from harness.reports.table_dp import pixel_markdown
from harness.runtime.cache import read_cached_parquet, write_text

log = logging.getLogger(__name__)

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
        s = np.atleast_2d(np.asarray(s, np.float64))
        ok = np.isfinite(s)
        low = np.where(ok, s, np.inf).min(axis=1, keepdims=True, initial=np.inf)
        low = np.where(np.isfinite(low), low, 0.0)
        s = np.where(ok, s, low)  # a box without a LoC (unaligned) scores as no box
        return np.where(self.unit[None, :] >= 0, s[:, np.maximum(self.unit, 0)], low)

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
    reg = register(q, mm, opt.keypoints, opt.difference)
    if not reg.comparable and opt.not_comparable == "fallback":
        reg = reg.fallback(q, mm, opt.difference, opt.local)
    made = difference_map(q, mm, reg, opt.difference)
    return box_differences(made, novelty_of(q, mm, opt.difference), boxes, opt.difference)

"""One chunk of ``harness detect``'s query frames: fusion, candidates, change boxes, frame scores.

Each chunk is a cache unit (an interrupted run resumes at the next one).
"""

from __future__ import annotations

import dataclasses
import logging
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.detect.boxes import candidate_boxes, change_boxes_nms, with_area_prior, with_prior
from harness.detect.config import DetectConfig
from harness.detect.difference import difference_contrast, difference_map
from harness.fusion.config import FusionConfig
from harness.fusion.samples import fuse_samples
from harness.imagestore import read_image
from harness.proposals.builtin import segment_boxes
from harness.proposals.config import SegmentsConfig
from harness.records import FRAME_KEY, QUERY_KEY, frame_sizes
from harness.runtime.cache import (
    stable_hash,
    write_parquet,
)
from harness.runtime.progress import progress

log = logging.getLogger(__name__)


#: A frame's result after its frame key and map session: its score (the largest LoC), the kept
#: boxes and fused samples, and the best box.
FRAME_RESULT = ["score", "boxes", "samples", "top_x1", "top_y1", "top_x2", "top_y2"]


def _all_no_change(qk: pd.DataFrame) -> pd.DataFrame:
    """Every query frame of a chunk as annotated "no-change": fusion then covers them all."""
    return pd.DataFrame(
        {
            "session": qk["q_session"].to_numpy(),
            "camera": qk["q_camera"].to_numpy(),
            "utime": qk["q_utime"].to_numpy(),
            "status": "no-change",
            "x1": np.nan,
            "y1": np.nan,
            "x2": np.nan,
            "y2": np.nan,
            "label": "",
        }
    )


def _frame_boxes_of(
    g: pd.DataFrame,
    floc: np.ndarray,
    orig: np.ndarray,
    size: tuple[int, int],
    fk: tuple[str, str, int],
    opt: DetectConfig,
    seed: int,
    difference: Any = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """One frame's candidate boxes and scores by ``opt.boxes``, kept by NMS, and the random row.

    ``g``: the frame's fused qBBs, ``floc`` their LoC; ``orig``: its original proposals. Returns
    candidates, their scores, the indices kept, the indices kept for random scores, those scores,
    how many candidates were thinner than ``opt.min_box_side`` (dropped before all of it) and each
    candidate's aligned difference (``difference(boxes)``; NaN where none is given).
    """
    fused = g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    if opt.boxes == "fused":
        boxes, loc, rnd = fused, floc, g["loc_random"].to_numpy(np.float64)
    elif opt.boxes == "subimages":  # each ranked subimage scored by its own r (method §13.3)
        boxes, loc = orig[:, :4], orig[:, 4]
        rnd = np.random.default_rng(int(stable_hash(seed, fk, length=8), 16)).random(len(boxes))
    else:
        boxes, loc = candidate_boxes(
            opt.boxes, fused, floc, orig, *size, opt.box_score, opt.locmap_level
        )
        # the random row: uniform scores on the same candidates, seeded by the frame
        rnd = np.random.default_rng(int(stable_hash(seed, fk, length=8), 16)).random(len(boxes))
    wide = np.minimum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) >= opt.min_box_side
    boxes, loc, rnd = boxes[wide], loc[wide], rnd[wide]
    diff = difference(boxes) if difference is not None else np.full(len(boxes), np.nan)
    if opt.box_prior == "area":
        loc = with_area_prior(boxes, loc)
    elif opt.box_prior == "difference":
        loc = with_prior(loc, diff)
    keep = change_boxes_nms(boxes, loc, opt.nms_iou, opt.max_boxes)
    rand = change_boxes_nms(boxes, rnd, opt.nms_iou, opt.max_boxes)
    return boxes, loc, keep, rand, rnd, int((~wide).sum()), diff


def _write_chunk(
    tmp: Path,
    cand_parts: list[pd.DataFrame],
    rows: list[tuple],
    frow: list[tuple],
    samples: pd.DataFrame,
    col: str,
) -> None:
    """A chunk's candidates, change boxes, frame rows and fused qBBs (LoC in ``col``)."""
    cands = (
        pd.concat(cand_parts, ignore_index=True)
        if cand_parts
        else pd.DataFrame(columns=[*QUERY_KEY, "x1", "y1", "x2", "y2", "loc", "difference"])
    )
    write_parquet(tmp / "candidates.parquet", cands)
    write_parquet(
        tmp / "boxes.parquet",
        pd.DataFrame(rows, columns=[*FRAME_KEY, "kind", "rank", "x1", "y1", "x2", "y2", "score"]),
    )
    write_parquet(
        tmp / "frames.parquet",
        pd.DataFrame(
            frow,
            columns=[*FRAME_KEY, "r_session", *FRAME_RESULT],
        ),
    )
    write_parquet(
        tmp / "samples.parquet",
        samples[[*QUERY_KEY, "x1", "y1", "x2", "y2", "N", col]].rename(columns={col: "loc"}),
    )


def _frame_boxes(
    ranks: pd.DataFrame, frames: pd.DataFrame, opt: DetectConfig, segments: SegmentsConfig
) -> dict[tuple[str, str, int], np.ndarray]:
    """Each query frame's boxes for the ``proposals`` or ``segments`` generator.

    Its original proposals (the rows of ``ranks``), or, for ``segments``, the colour regions of
    its image (:func:`harness.proposals.builtin.segment_boxes`, read one frame at a time).
    """
    if opt.boxes == "subimages":  # (x1, y1, x2, y2, r): r the mean over localizers of a box
        return {
            (str(k[0]), str(k[1]), int(k[2])): g.groupby(["x1", "y1", "x2", "y2"], sort=True)["r"]
            .mean()
            .reset_index()
            .to_numpy(np.float64)
            for k, g in ranks.groupby(QUERY_KEY, sort=False)
        }
    out = {
        (str(k[0]), str(k[1]), int(k[2])): g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
        for k, g in ranks.groupby(QUERY_KEY, sort=False)
    }
    if opt.boxes == "segments":
        images = frames.set_index(FRAME_KEY)["image"]
        for k in out:
            out[k] = segment_boxes(read_image(images.loc[k]), segments)[0]
    return out


def _difference(images: pd.Series, fk: tuple[str, str, int], paired: dict) -> Any:
    """``boxes -> their aligned-difference contrast`` for query frame ``fk`` and its map frame.

    :mod:`harness.detect.difference`; the pair's difference map is computed once, on first use.
    """
    made: list[tuple[np.ndarray, float]] = []

    def scores(boxes: np.ndarray) -> np.ndarray:
        if not made:
            made.append(
                difference_map(read_image(images.loc[fk]), read_image(images.loc[paired[fk]]))
            )
        return difference_contrast(*made[0], boxes)

    return scores


def detect_chunk(
    ranks: pd.DataFrame,
    frames: pd.DataFrame,
    opt: DetectConfig,
    fusion: FusionConfig,
    segments: SegmentsConfig,
    tmp: Path,
    null: bool = False,
) -> dict[str, int]:
    """Fusion, change boxes and frame scores of one chunk of query frames into ``tmp``.

    ``null``: the chunk is of the no-change null's pairs (:mod:`harness.detect.null`), whose
    candidates feed no Table D: their aligned difference is computed only where the box prior
    reads it.

    ``opt``: the run's ``[detect]`` (its rule among them); ``fusion``: the config's ``[fusion]``
    (the seed, the cap on fused boxes, RRF's constant, a registered rule's options);
    ``segments``: ``[proposals.segments]``, the colour regions of the ``segments`` generator.

    ``boxes.parquet``: every change box (frame key, rank within the frame, box, LoC);
    ``frames.parquet``: one row per frame (key, map frame, score, boxes, samples); and, for the
    LoC maps drawn later, ``samples.parquet`` (every fused qBB with its LoC).
    """
    qk = ranks[QUERY_KEY].drop_duplicates()
    ann = _all_no_change(qk)
    samples, counts = fuse_samples(
        ranks,
        frames,
        ann,
        dataclasses.replace(fusion, methods=(opt.fusion, "random")),
        progress=partial(progress, desc="detect", unit="frame"),
    )
    samples = samples[samples["proposal_method"] == "all"].reset_index(drop=True)
    col = f"loc_{opt.fusion}"
    size = frame_sizes(frames)
    orig = _frame_boxes(ranks, frames, opt, segments)
    images = frames.set_index(FRAME_KEY)["image"]
    paired = {  # each query frame's map frame
        (str(k[0]), str(k[1]), int(k[2])): (str(r.r_session), str(r.r_camera), int(r.r_utime))
        for k, r in ranks.groupby(QUERY_KEY, sort=False).first().iterrows()
    }
    rows, frow, cand_parts, thin = [], [], [], 0
    for key, g in samples.groupby([*QUERY_KEY, "r_session"], sort=True):
        fk = (str(key[0]), str(key[1]), int(key[2]))
        floc = g[col].to_numpy(np.float64)
        diff = None if null and opt.box_prior != "difference" else _difference(images, fk, paired)
        found = _frame_boxes_of(g, floc, orig[fk], size[fk], fk, opt, fusion.seed, diff)
        boxes, loc, keep, rand, rnd, n_thin, diff = found
        thin += n_thin
        for kind, idx, sc in (("detection", keep, loc), ("random", rand, rnd)):
            for j, i in enumerate(idx):
                rows.append((*key[:3], kind, j, *boxes[i], float(sc[i])))
        cand_parts.append(
            pd.DataFrame(
                {
                    "q_session": fk[0],
                    "q_camera": fk[1],
                    "q_utime": np.full(len(boxes), fk[2], np.int64),
                    **{c: boxes[:, j] for j, c in enumerate(("x1", "y1", "x2", "y2"))},
                    "loc": loc,
                    "difference": diff,
                }
            )
        )
        top = boxes[keep[0]] if len(keep) else np.full(4, np.nan)
        frow.append(
            (
                *key,
                float(np.nanmax(floc)) if np.isfinite(floc).any() else np.nan,
                len(keep),
                len(g),
                *top,
            )
        )
    _write_chunk(tmp, cand_parts, rows, frow, samples, col)
    return {
        "frames": len(frow),
        "capped_closures": int(counts.get("capped_closures", 0)),
        "thin_boxes_dropped": thin,
    }

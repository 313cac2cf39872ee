"""One chunk of ``harness detect``'s query frames: fusion, candidates, change boxes, frame scores.

Each chunk is a cache unit (an interrupted run resumes at the next one).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.boxes import greedy_nms, suppression
from harness.detect.boxes import candidate_boxes, with_area_prior, with_prior
from harness.detect.config import DetectConfig
from harness.detect.pair import PairDifference, PairFeatures
from harness.detect.plain import reference_boxes
from harness.fusion.config import FusionConfig
from harness.fusion.samples import fuse_samples
from harness.imagestore import read_image
from harness.proposals.builtin import segment_boxes, selective_boxes
from harness.proposals.config import ProposalsConfig, SegmentsConfig, SelectiveConfig
from harness.records import FRAME_KEY, QUERY_KEY, frame_groups, frame_sizes
from harness.runtime.cache import stable_hash, write_parquet
from harness.runtime.progress import progress

log = logging.getLogger(__name__)


#: A frame's result after its frame key and map session: its score (the largest LoC), the kept
#: boxes and fused samples, the best box, and the pair's registration (docs/decisions.md, *The plain
#: difference*): whether it is comparable, its homography's inliers, why not where it is not, and
#: what its difference was read through (homography; a fallback's ecc or identity; none), and the
#: registration as a similarity (the centre's shift as shares of the frame, rotation, scale):
#: what the no-change null's copies are drawn from (docs/decisions.md, *Calibrated alarms*), with
#: what the homography leaves (the matches' median residual, a share of the diagonal: parallax).
FRAME_RESULT = [
    "score", "boxes", "samples", "top_x1", "top_y1", "top_x2", "top_y2",
    "comparable", "inliers", "not_comparable_why", "compared_by",
    "reg_dx", "reg_dy", "reg_rotation_deg", "reg_scale", "reg_residual",
]  # fmt: skip


@dataclass(frozen=True)
class _Fused:
    """One frame's fused qBBs: their boxes (n, 4), LoC and random scores (the ``random`` rule)."""

    boxes: np.ndarray
    loc: np.ndarray
    random: np.ndarray


def _fused_by_frame(samples: pd.DataFrame, col: str) -> list[tuple[tuple, _Fused]]:
    """Each (query frame, map session)'s fused qBBs as arrays, in ``groupby``'s sorted order."""
    gb = samples.groupby([*QUERY_KEY, "r_session"], sort=True)
    at = gb.indices
    xy = samples[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    loc = samples[col].to_numpy(np.float64)
    rnd = (samples["loc_random"] if "loc_random" in samples else samples[col]).to_numpy(np.float64)
    return [(k, _Fused(xy[at[k]], loc[at[k]], rnd[at[k]])) for k in gb.size().index]


def _frame_boxes_of(
    g: _Fused,
    floc: np.ndarray,
    orig: np.ndarray,
    size: tuple[int, int],
    fk: tuple[str, str, int],
    opt: DetectConfig,
    seed: int,
    pair: PairDifference | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """One frame's candidate boxes and scores by ``opt.boxes``, kept by NMS, and the random row.

    ``g``: the frame's fused qBBs, ``floc`` their LoC; ``orig``: its original proposals. Returns
    candidates, their scores, the indices kept, the indices kept for random scores, those scores,
    how many candidates were thinner than ``opt.min_box_side`` (dropped before all of it) and each
    candidate's plain difference (``pair.contrast(boxes)``; NaN where no pair is given); a
    difference prior's scores are lifted by the pair's tier (:class:`PairDifference`).
    """
    fused = g.boxes
    if opt.boxes == "fused":
        boxes, loc, rnd = fused, floc, g.random
    else:
        if opt.boxes == "subimages":  # each ranked subimage scored by its own r (method §13.3)
            boxes, loc = orig[:, :4], orig[:, 4]
        else:
            boxes, loc = candidate_boxes(
                opt.boxes, fused, floc, orig, *size, opt.box_score, opt.locmap_level
            )
        # the random row: uniform scores on the same candidates, seeded by the frame
        rnd = np.random.default_rng(int(stable_hash(seed, fk, length=8), 16)).random(len(boxes))
    wide = np.minimum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) >= opt.min_box_side
    boxes, loc, rnd = boxes[wide], loc[wide], rnd[wide]
    diff = pair.contrast(boxes) if pair is not None else np.full(len(boxes), np.nan)
    tier = pair.tier if pair is not None else 0.0
    if opt.box_prior == "area":
        loc = with_area_prior(boxes, loc)
    elif opt.box_prior == "difference":
        loc = with_prior(loc, diff) + tier
    elif opt.box_prior == "difference_product":
        loc = np.maximum(diff, 0.0) * loc**opt.localization_weight + tier
    sup = suppression(boxes, opt.nms_iou)  # the same boxes for both
    keep = greedy_nms(boxes, loc, opt.nms_iou, opt.max_boxes, sup)
    rand = greedy_nms(boxes, rnd, opt.nms_iou, opt.max_boxes, sup)
    return boxes, loc, keep, rand, rnd, int((~wide).sum()), diff


def _write_chunk(
    tmp: Path,
    cand_parts: list[tuple[tuple, np.ndarray, np.ndarray, np.ndarray]],
    rows: list[tuple],
    frow: list[tuple],
    samples: pd.DataFrame,
    col: str,
) -> None:
    """A chunk's candidates, change boxes, frame rows and fused qBBs (LoC in ``col``)."""
    write_parquet(tmp / "candidates.parquet", _candidates(cand_parts))
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
    xy = ranks[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    out = {k: xy[rows] for k, rows in frame_groups(ranks)}
    if opt.boxes == "segments":
        images = frames.set_index(FRAME_KEY)["image"]
        for k in out:
            out[k] = segment_boxes(read_image(images.loc[k]), segments)[0]
    return out


def _pair(
    images: pd.Series, fk: tuple, mk: tuple, opt: DetectConfig, feats: PairFeatures
) -> PairDifference:
    """Query frame ``fk`` and its map frame ``mk`` compared once (:class:`PairDifference`)."""
    q, m = read_image(images.loc[fk]), read_image(images.loc[mk])
    return PairDifference(q, m, opt, feats, (str(images.loc[fk]), str(images.loc[mk])))


#: A frame row's registration columns where neither the detector nor Table D reads one
#: (:func:`reads_registration`): compared by localization alone, so comparable; not registered.
UNREGISTERED_ROW = (True, 0, "", "not registered", *(float("nan"),) * 5)


def reads_registration(opt: DetectConfig) -> bool:
    """Whether the detector's own boxes read each pair's registration and plain difference.

    A box prior of the difference does, and ``not_comparable = "drop"`` (a pair is dropped by
    its registration). The paper's detector (``box_prior = "none"``) scores boxes by their LoC
    alone: its pairs are registered only where Table D's plain difference reads them.
    """
    return opt.box_prior in ("difference", "difference_product") or opt.not_comparable == "drop"


def _plain_difference(
    pair: PairDifference,
    fk: tuple,
    opt: DetectConfig,
    selective: SelectiveConfig,
    known: np.ndarray | None = None,
) -> pd.DataFrame:
    """The plain difference's own candidates of one query frame.

    Selective Search's boxes of the query image scored by the difference (none where the pair was
    compared by nothing); ``known``: those boxes where the detector ranked them already.
    """
    if pair.made is None:
        boxes = np.zeros((0, 4))
    elif opt.difference.recipe == "reference":  # every box of Selective Search (its step 4)
        boxes = reference_boxes(pair.q, selective.work_width, selective.mode, selective.seed)
    elif known is not None:
        boxes = np.unique(np.asarray(known, np.float64).reshape(-1, 4), axis=0)
    else:
        boxes = selective_boxes(pair.q, selective)[0]
    sc = pair.score(boxes)
    return pd.DataFrame(
        {
            "q_session": fk[0],
            "q_camera": fk[1],
            "q_utime": np.full(len(boxes), fk[2], np.int64),
            **{c: boxes[:, j] for j, c in enumerate(("x1", "y1", "x2", "y2"))},
            "difference": sc,
        }
    )


def _candidates(parts: list[tuple[tuple, np.ndarray, np.ndarray, np.ndarray]]) -> pd.DataFrame:
    """The chunk's candidates, one table of each frame's (key, boxes, scores, difference)."""
    if not parts:
        return pd.DataFrame(columns=[*QUERY_KEY, "x1", "y1", "x2", "y2", "loc", "difference"])
    n = [len(b) for _, b, _, _ in parts]
    boxes = np.concatenate([b.reshape(-1, 4) for _, b, _, _ in parts])
    key = [np.array([fk[i] for fk, *_ in parts], object) for i in (0, 1)]
    return pd.DataFrame(
        {
            "q_session": np.repeat(key[0], n),
            "q_camera": np.repeat(key[1], n),
            "q_utime": np.repeat(np.array([fk[2] for fk, *_ in parts], np.int64), n),
            **{c: boxes[:, j] for j, c in enumerate(("x1", "y1", "x2", "y2"))},
            "loc": np.concatenate([x for _, _, x, _ in parts]),
            "difference": np.concatenate([x for *_, x in parts]),
        }
    )


def _registration_row(pair: PairDifference) -> tuple:
    """A frame row's registration columns (:data:`FRAME_RESULT`'s last nine)."""
    r = pair.reg
    used = pair.used.method if pair.made is not None else "none"
    res = r.residual if r.comparable else float("nan")
    return (r.comparable, r.inliers, r.why, used, *r.similarity(pair.q.shape[1], pair.q.shape[0]),
            res)  # fmt: skip


@dataclass(frozen=True)
class _Frame:
    """What one query frame's result reads (:meth:`result`, one frame a thread).

    The chunk's fused LoC column, images, pairs, original boxes and sizes, the options, the
    random row's seed, ``[proposals]``, the frames whose plain difference Table D reads, and the
    keypoints detected so far.
    """

    col: str
    images: pd.Series
    paired: dict[tuple[str, str, int], tuple[str, str, int]]
    orig: dict[tuple[str, str, int], np.ndarray]
    size: dict[Any, tuple[int, int]]
    opt: DetectConfig
    seed: int
    proposals: ProposalsConfig
    plain_for: frozenset[tuple[str, str, int]]
    feats: PairFeatures

    def result(self, key: tuple, g: _Fused) -> tuple[list[tuple], tuple, tuple, Any, int]:
        """One query frame's change boxes, frame row, candidates and plain difference."""
        opt, fk = self.opt, (str(key[0]), str(key[1]), int(key[2]))
        floc = g.loc
        pair = None
        if fk in self.plain_for or reads_registration(opt):
            pair = _pair(self.images, fk, self.paired[fk], opt, self.feats)
        found = _frame_boxes_of(g, floc, self.orig[fk], self.size[fk], fk, opt, self.seed, pair)
        boxes, loc, keep, rand, rnd, n_thin, diff = found
        if pair is not None and not pair.reg.comparable and opt.not_comparable == "drop":
            # nothing to compare: no box, no score, no candidate (docs/method.md)
            boxes, loc, diff = boxes[:0], loc[:0], diff[:0]
            keep, rand = keep[:0], rand[:0]
            floc = floc[:0]
        plain = None
        if pair is not None and fk in self.plain_for:
            # the detector's own proposals where they are Selective Search's (one search a frame)
            known = self.orig[fk][:, :4] if opt.proposals == "selective" and opt.boxes in (
                "subimages", "proposals") else None  # fmt: skip
            plain = _plain_difference(pair, fk, opt, self.proposals.selective, known)
        rows = [
            (*key[:3], kind, j, *boxes[i], float(sc[i]))
            for kind, idx, sc in (("detection", keep, loc), ("random", rand, rnd))
            for j, i in enumerate(idx)
        ]
        top = boxes[keep[0]] if len(keep) else np.full(4, np.nan)
        score = float(np.nanmax(floc)) if np.isfinite(floc).any() else np.nan
        reg = UNREGISTERED_ROW if pair is None else _registration_row(pair)
        frow = (*key, score, len(keep), len(g.loc), *top, *reg)
        return rows, frow, (fk, boxes, loc, diff), plain, n_thin


def detect_chunk(
    ranks: pd.DataFrame,
    frames: pd.DataFrame,
    opt: DetectConfig,
    fusion: FusionConfig,
    proposals: ProposalsConfig,
    tmp: Path,
    plain_for: frozenset[tuple[str, str, int]] = frozenset(),
) -> dict[str, int]:
    """Fusion, change boxes and frame scores of one chunk of query frames into ``tmp``.

    ``plain_for``: the query frames whose plain difference's own candidates Table D reads (the
    annotated ones; none for the no-change null's pairs, :mod:`harness.detect.null`): only
    those frames pay for its Selective Search.

    ``opt``: the run's ``[detect]`` (its rule among them); ``fusion``: the config's ``[fusion]``
    (the seed, the cap on fused boxes, RRF's constant, a registered rule's options);
    ``proposals``: ``[proposals]``, whose ``segments`` are the colour regions of the ``segments``
    generator and whose ``selective`` boxes are the plain difference's own.

    Every pair whose registration the detector or Table D reads is registered first
    (:mod:`harness.detect.difference`, :func:`reads_registration`); a pair that is not
    comparable keeps no change box and no score where ``[detect] not_comparable = "drop"``.

    ``boxes.parquet``: every change box (frame key, rank within the frame, box, LoC);
    ``frames.parquet``: one row per frame (key, map frame, score, boxes, samples, registration);
    ``plain_difference.parquet``: the plain difference's candidates and their contrast; and, for
    the LoC maps drawn later, ``samples.parquet`` (every fused qBB with its LoC).
    """
    threads = opt.threads if opt.threads > 0 else len(os.sched_getaffinity(0))
    samples, counts = fuse_samples(  # every frame, unlabelled: detect reads no annotation
        ranks,
        frames,
        None,
        dataclasses.replace(fusion, methods=(opt.fusion, "random")),
        progress=partial(progress, desc="detect", unit="frame"),
        threads=threads,
    )
    samples = samples[samples["proposal_method"] == "all"].reset_index(drop=True)
    col = f"loc_{opt.fusion}"
    size = frame_sizes(frames)
    orig = _frame_boxes(ranks, frames, opt, proposals.segments)
    images = frames.set_index(FRAME_KEY)["image"]
    ref = ranks[["r_session", "r_camera", "r_utime"]].to_numpy(object)
    paired = {  # each query frame's map frame: its first row's
        k: (str(ref[rows[0], 0]), str(ref[rows[0], 1]), int(ref[rows[0], 2]))
        for k, rows in frame_groups(ranks)
    }
    feats = PairFeatures(opt.keypoints)  # a frame in several pairs (the null's): detected once
    frame = _Frame(col, images, paired, orig, size, opt, fusion.seed, proposals, plain_for, feats)
    rows, frow, cand_parts, plain_parts, thin = [], [], [], [], 0
    groups = _fused_by_frame(samples, col)
    with ThreadPoolExecutor(threads, thread_name_prefix="detect") as pool:  # in the frames' order
        for f_rows, f_row, cands, plain, n_thin in pool.map(lambda kg: frame.result(*kg), groups):
            rows += f_rows
            frow.append(f_row)
            cand_parts.append(cands)
            if plain is not None:
                plain_parts.append(plain)
            thin += n_thin
    _write_chunk(tmp, cand_parts, rows, frow, samples, col)
    empty = pd.DataFrame(columns=[*QUERY_KEY, "x1", "y1", "x2", "y2", "difference"])
    plain = pd.concat(plain_parts, ignore_index=True) if plain_parts else empty
    write_parquet(tmp / "plain_difference.parquet", plain)
    return {
        "frames": len(frow),
        "capped_closures": int(counts.get("capped_closures", 0)),
        "thin_boxes_dropped": thin,
    }

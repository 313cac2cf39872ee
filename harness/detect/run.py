"""``harness detect``: the maintenance-free change detector on a robot's new session (SPEC 13).

Given a map (reference) session and one or more new (query) sessions of a config, every query
frame (thinned by ``[pairs] stride_m``) is paired with the map by pose (SPEC section 4), its
subimages are ranked by the config's localizer(s) (SPEC sections 6 and 11), and the ranks are
fused (SPEC section 7, ``--fusion``, default ``rank_fusion``; across localizers when there
are several) into:

- change boxes: the fused qBBs in descending LoC after greedy non-maximum suppression at IoU
  ``[detect] nms_iou`` (OpenCV's ``dnn.NMSBoxes``), at most ``max_boxes`` per frame;
- the frame's change score: the largest LoC of its samples;
- the pixel-wise LoC map of the frames shown (float16 arrays and colour overlays).

Annotations are optional; where some query frames are annotated, the detections are scored
(Table D) with pycocotools: box AP at IoU 0.5 with VOC all-point interpolation (the metric of "The
Change You Want to See", WACV 2023) and COCO AP@[.5:.95], beside a floor (random scores on the
same fused qBBs, through the same NMS). Work is cached per chunk of query frames (an interrupted
run resumes at the next chunk) and mapped through the run's executor (local or Ray).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
from scipy.stats import rankdata

from harness import kernels
from harness.config.schema import (
    ALL_LOCALIZERS,
    Config,
    LocalConfig,
    LocalizerConfig,
    SegmentsConfig,
)
from harness.detect.pixels import write_pixel_table
from harness.errors import ConfigError, HarnessError
from harness.fusion.fuse import fuse_samples, loc_map
from harness.imagestore import read_image
from harness.ingest.names import session_names, with_names
from harness.methods import BOX_GENERATORS, BOX_SCORES
from harness.pairs import BY_RETRIEVAL
from harness.pipeline import keys
from harness.proposals.proposers import segment_boxes
from harness.records import FRAME_KEY, QUERY_KEY, frame_sizes
from harness.runtime.cache import (
    read_cached_parquet,
    stable_hash,
    write_json,
    write_parquet,
    write_text,
)
from harness.runtime.progress import progress

log = logging.getLogger(__name__)

#: The proposal method ``harness detect``'s local localizer ranks: the frame's colour regions,
#: which meet most change objects (docs/method.md, *Detect*).
LOCAL_PROPOSALS = "segments"

#: What a pair not made by pose adds to its query frame's row (SPEC 13.2).
PAIR_EXTRA = ("pair_confidence", "uncertain_pair")

#: A frame's result after its frame key and map session: its score (the largest LoC), the kept
#: boxes and fused samples, and the best box.
FRAME_RESULT = ["score", "boxes", "samples", "top_x1", "top_y1", "top_x2", "top_y2"]


@dataclass(frozen=True)
class DetectOptions:
    """``harness detect``'s choices (SPEC 13); defaults are SPEC's."""

    fusion: str = "rank_fusion"
    nms_iou: float = 0.5
    max_boxes: int = 10
    chunk_frames: int = 64  # query frames per cached unit (the unit a killed run resumes at)
    top: int = 10  # most changed places on the map and the page
    seed: int = 0
    boxes: str = "subimages"  # the box generator (SPEC 13.1, [detect] boxes)
    box_score: str = "max"  # locmap / proposals / segments: max, mean or contrast of the LoC
    locmap_level: float = 0.5  # locmap: the level, a share of the frame's LoC range
    min_box_side: float = 2.0  # [detect] min_box_side: thinner candidates are dropped
    segments: SegmentsConfig = field(default_factory=SegmentsConfig)  # [proposals.segments]
    localizer: str = "local"  # [detect] localizer: "local" (SPEC 13.3) or "config"
    box_prior: str = "area"  # [detect] box_prior: "area" or "none" (SPEC 13.3)
    local: LocalConfig = field(default_factory=LocalConfig)  # [detect.local]

    def record(self) -> dict[str, Any]:
        """The options as ``detect.json`` and the cache keys hold them (``segments`` where used)."""
        out = dataclasses.asdict(self)
        if self.boxes != "segments" and self.localizer != "local":
            del out["segments"]
        if self.localizer != "local":  # the paper's detector: its record (and keys) as before
            del out["local"], out["localizer"]
        return out

    def local_localizer(self) -> LocalizerConfig | None:
        """The local localizer ``[detect] localizer = "local"`` measures (None: the config's)."""
        if self.localizer != "local":
            return None
        return LocalizerConfig("local", "local", (LOCAL_PROPOSALS,), self.local)


def change_boxes_nms(
    boxes: np.ndarray, loc: np.ndarray, nms_iou: float, max_boxes: int
) -> np.ndarray:
    """Indices of the kept boxes: descending LoC, greedy NMS at ``nms_iou``, at most ``max_boxes``.

    OpenCV's ``dnn.NMSBoxes`` on (x, y, w, h); boxes without a finite LoC never enter.
    """
    ok = np.flatnonzero(np.isfinite(loc))
    if not len(ok):
        return np.zeros(0, np.int64)
    b = boxes[ok]
    xywh = np.column_stack([b[:, 0], b[:, 1], b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]])
    order = np.argsort(-loc[ok], kind="stable")  # ties: the earlier box first, every run
    xywh, sc, ok = xywh[order], loc[ok][order], ok[order]
    # scores are shifted to [0, 1] order-preservingly: NMSBoxes' threshold is on raw scores
    rank_score = (np.arange(len(sc), 0, -1) / len(sc)).astype(np.float32)
    keep = cv2.dnn.NMSBoxes(
        [tuple(map(float, r)) for r in xywh], rank_score.tolist(), 0.0, nms_iou, top_k=max_boxes
    )
    idx = np.asarray(keep, np.int64).reshape(-1)
    idx = idx[np.argsort(-rank_score[idx], kind="stable")][:max_boxes]
    return ok[idx].astype(np.int64)


def _pixels(m: np.ndarray, box: np.ndarray) -> tuple[int, int, int, int]:
    """The pixel rows and columns (v0, v1, u0, u1) whose centres lie in ``box``."""
    h, w = m.shape
    x1, y1, x2, y2 = box
    u0, u1 = max(int(np.ceil(x1 - 0.5)), 0), min(int(np.ceil(x2 - 0.5)), w)
    v0, v1 = max(int(np.ceil(y1 - 0.5)), 0), min(int(np.ceil(y2 - 0.5)), h)
    return v0, v1, u0, u1


def _inside(m: np.ndarray, box: np.ndarray, how: str) -> float:
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
    """A frame's candidate change boxes and their scores under a box generator (SPEC 13.1).

    ``fused``: the fused qBBs and their LoC. ``proposals`` and ``segments``: the boxes
    ``originals`` (the frame's original proposals, or its colour regions), duplicates merged, each
    scored by the ``how`` (:func:`_inside`) of the pixel-wise LoC map. ``locmap``: the LoC map
    thresholded at ``lo + level * (hi - lo)`` of the frame's range, the bounding boxes of its
    8-connected regions (``cv2.connectedComponentsWithStats``), each scored by the ``how`` of the
    LoC over the region's own pixels (``contrast``: over its box, as :func:`_inside`).

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
        return boxes, np.array([_inside(m, b, how) for b in boxes], np.float64)
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
            scores.append(_inside(m, np.array(found[-1], np.float64), how))
        else:
            scores.append(float(vals.max() if how == "max" else vals.mean()))
    return np.asarray(found, np.float64).reshape(-1, 4), np.asarray(scores, np.float64)


def _nms(boxes: np.ndarray, scores: np.ndarray, nms_iou: float, max_boxes: int) -> np.ndarray:
    """The detector's NMS as a function of (boxes, scores), for Table D's chance draws."""
    return change_boxes_nms(boxes, scores, nms_iou, max_boxes)


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


def with_area_prior(boxes: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Scores fused with box area (``[detect] box_prior = "area"``, SPEC 13.3).

    Each box's score becomes the mean of its percentile among the frame's scored boxes by
    ``score`` and by area (``(rank - 0.5) / n``, ties sharing their mean rank); a box without a
    finite score keeps none. Within-frame percentiles put every frame on one scale, so the
    pooled ranking does not follow whichever frames happen to score high overall; the area
    part is the prior a no-pixel baseline reads, so Table D's paired test against box area
    alone measures what the pixels add.
    """
    out = np.full(len(score), np.nan)
    ok = np.isfinite(score)
    n = int(ok.sum())
    if n:
        b = boxes[ok]
        area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
        out[ok] = ((rankdata(score[ok]) - 0.5) / n + (rankdata(area) - 0.5) / n) / 2
    return out


def _frame_boxes_of(
    g: pd.DataFrame,
    floc: np.ndarray,
    orig: np.ndarray,
    size: tuple[int, int],
    fk: tuple[str, str, int],
    opt: DetectOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """One frame's candidate boxes and scores by ``opt.boxes``, kept by NMS, and the random row.

    ``g``: the frame's fused qBBs, ``floc`` their LoC; ``orig``: its original proposals. Returns
    candidates, their scores, the indices kept, the indices kept for random scores, those scores
    and how many candidates were thinner than ``opt.min_box_side`` (dropped before all of it).
    """
    fused = g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    if opt.boxes == "fused":
        boxes, loc, rnd = fused, floc, g["loc_random"].to_numpy(np.float64)
    elif opt.boxes == "subimages":  # each ranked subimage scored by its own r (SPEC 13.3)
        boxes, loc = orig[:, :4], orig[:, 4]
        rnd = np.random.default_rng(int(stable_hash(opt.seed, fk, length=8), 16)).random(len(boxes))
    else:
        boxes, loc = candidate_boxes(
            opt.boxes, fused, floc, orig, *size, opt.box_score, opt.locmap_level
        )
        # the random row: uniform scores on the same candidates, seeded by the frame
        rnd = np.random.default_rng(int(stable_hash(opt.seed, fk, length=8), 16)).random(len(boxes))
    wide = np.minimum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) >= opt.min_box_side
    boxes, loc, rnd = boxes[wide], loc[wide], rnd[wide]
    if opt.box_prior == "area":
        loc = with_area_prior(boxes, loc)
    keep = change_boxes_nms(boxes, loc, opt.nms_iou, opt.max_boxes)
    rand = change_boxes_nms(boxes, rnd, opt.nms_iou, opt.max_boxes)
    return boxes, loc, keep, rand, rnd, int((~wide).sum())


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
        else pd.DataFrame(columns=[*QUERY_KEY, "x1", "y1", "x2", "y2", "loc"])
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
    ranks: pd.DataFrame, frames: pd.DataFrame, opt: DetectOptions
) -> dict[tuple[str, str, int], np.ndarray]:
    """Each query frame's boxes for the ``proposals`` or ``segments`` generator.

    Its original proposals (the rows of ``ranks``), or, for ``segments``, the colour regions of
    its image (:func:`harness.proposals.proposers.segment_boxes`, read one frame at a time).
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
            out[k] = segment_boxes(read_image(images.loc[k]), opt.segments)[0]
    return out


def detect_chunk(
    ranks: pd.DataFrame,
    frames: pd.DataFrame,
    opt: DetectOptions,
    max_fused: int,
    rrf_c: float,
    tmp: Path,
) -> dict[str, int]:
    """Fusion, change boxes and frame scores of one chunk of query frames into ``tmp``.

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
        opt.seed,
        max_fused,
        methods=(opt.fusion, "random"),
        progress=partial(progress, desc="detect", unit="frame"),
        rrf_c=rrf_c,
    )
    samples = samples[samples["proposal_method"] == "all"].reset_index(drop=True)
    col = f"loc_{opt.fusion}"
    size = frame_sizes(frames)
    orig = _frame_boxes(ranks, frames, opt)
    rows, frow, cand_parts, thin = [], [], [], 0
    for key, g in samples.groupby([*QUERY_KEY, "r_session"], sort=True):
        fk = (str(key[0]), str(key[1]), int(key[2]))
        floc = g[col].to_numpy(np.float64)
        boxes, loc, keep, rand, rnd, n_thin = _frame_boxes_of(g, floc, orig[fk], size[fk], fk, opt)
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


def check_detect_args(
    cfg: Config,
    map_session: str,
    query_sessions: list[str],
    opt: DetectOptions,
    rerun: Path | None,
    alarm: float | None,
) -> float:
    """The nominal false-alarm rate, after checking every argument of :func:`run_detect`.

    Raises:
        ConfigError: an unknown or repeated session, the map among the queries, an unknown
            method or box generator, a rate or NMS option out of range.
    """
    from harness.methods import detect_methods

    names = [s.name for s in cfg.sessions]
    for s in [map_session, *query_sessions]:
        if s not in names:
            raise ConfigError(f"detect: session {s!r} is not in the config; sessions: {names}")
    if map_session in query_sessions or len(set(query_sessions)) != len(query_sessions):
        raise ConfigError(
            f"detect: --map {map_session} and --query {query_sessions}: each session once, the "
            "map not among the queries"
        )
    if opt.fusion not in detect_methods():
        raise ConfigError(f"detect: method {opt.fusion!r}: one of {', '.join(detect_methods())}")
    if rerun is not None:
        check_rerun_target(Path(rerun))  # before any work: the SDK is there, the path is ours
    alarm = cfg.detect.alarm if alarm is None else alarm
    if not 0 < alarm < 1:
        raise ConfigError(f"detect: --alarm {alarm}: a false-alarm rate in (0, 1), e.g. 0.01")
    if opt.boxes not in BOX_GENERATORS:
        raise ConfigError(f"detect: --boxes {opt.boxes!r}: one of {', '.join(BOX_GENERATORS)}")
    if opt.box_score not in BOX_SCORES:
        raise ConfigError(f"detect: box_score {opt.box_score!r}: one of {', '.join(BOX_SCORES)}")
    if not 0 < opt.nms_iou <= 1 or opt.max_boxes < 1:
        raise ConfigError(
            f"detect: nms_iou {opt.nms_iou} must be in (0, 1] and max_boxes {opt.max_boxes} >= 1"
        )
    return alarm


def _measure(
    p: Any, map_session: str, query_sessions: list[str], local: LocalizerConfig | None
) -> tuple[Any, Any, Any, list]:
    """Frames, annotations, pairs and each localizer's ranks and fusion.

    Pairs by pose, or by retrieval where the config says so (SPEC 13.2). ``local``: the local
    localizer that ranks every pair's subimages instead of the config's (SPEC 13.3).
    """
    from harness.pipeline.chain import pairs_by_retrieval, until_annotations
    from harness.pipeline.localizer_stages import Measured, localizer_fusion, localizer_ranks
    from harness.pipeline.stages import session_proposals

    if p.cfg.pairs.by in BY_RETRIEVAL:  # sessions without poses (SPEC 13.2)
        ingested, frames, ann = until_annotations(p)
        pairs, m = pairs_by_retrieval(
            p, ingested, frames, ann, False, (map_session, tuple(query_sessions))
        )
        if local is None:
            return frames, ann, pairs, [m]
    else:
        ingested, frames, ann, pairs = detect_pairs(p, map_session, query_sessions)
    props = session_proposals(p, frames, pairs, ingested)
    measured = []
    for loc in (local,) if local is not None else p.localizer_list:
        ranks = localizer_ranks(p, loc, frames, pairs, props)
        fusion, notes = localizer_fusion(p, loc, ranks, len(pairs.df))
        measured.append(Measured(loc, ranks, fusion, notes))
    return frames, ann, pairs, measured


def _detect_config(
    cfg: Config, map_session: str, query_sessions: list[str], opt: DetectOptions
) -> Config:
    """The config ``detect`` runs: its sessions, every query frame, and the local proposals."""
    keep = [s for s in cfg.sessions if s.name in (map_session, *query_sessions)]
    dcfg = dataclasses.replace(
        cfg, sessions=tuple(keep), pairs=dataclasses.replace(cfg.pairs, queries="all")
    )
    if opt.localizer == "local" and LOCAL_PROPOSALS not in cfg.proposals.methods:
        methods = (*cfg.proposals.methods, LOCAL_PROPOSALS)
        dcfg = dataclasses.replace(
            dcfg,
            proposals=dataclasses.replace(cfg.proposals, methods=methods, segments=opt.segments),
            # the config's localizers (pairs by retrieval or sequence) keep their own proposals
            localizers=cfg.localizer_set(),
        )
    return dcfg


def _chunk_units(
    ranks: Any, frames: pd.DataFrame, opt: DetectOptions, dcfg: Config
) -> list[tuple[tuple[Any, ...], Any]]:
    """(cache key, build) of each chunk of ``opt.chunk_frames`` query frames.

    The build is :func:`detect_chunk` on the chunk's ranks.
    """
    chunk_units: list[tuple[tuple[Any, ...], Any]] = []
    qframes = ranks.df[QUERY_KEY].drop_duplicates().sort_values(QUERY_KEY).reset_index(drop=True)
    for c0 in range(0, len(qframes), opt.chunk_frames):
        part = qframes.iloc[c0 : c0 + opt.chunk_frames]
        mask = pd.MultiIndex.from_frame(ranks.df[QUERY_KEY]).isin(pd.MultiIndex.from_frame(part))
        build = partial(
            detect_chunk,
            ranks.df[mask].reset_index(drop=True),
            frames,
            opt,
            dcfg.fusion.max_fused_boxes,
            dcfg.fusion.rrf_c,
        )
        key = (
            "detect",
            ranks.key,
            opt.record() | {"chunk_frames": None},
            c0,
            len(part),
            keys.fusion_method_fingerprints((opt.fusion,)),
            *((dcfg.fusion.rrf_c,) if opt.fusion == "rrf" else ()),
        )
        chunk_units.append((key, build))
    return chunk_units


def run_detect(
    cfg: Config,
    map_session: str,
    query_sessions: list[str],
    out: Path,
    opt: DetectOptions | None = None,
    executor: Any = None,
    rerun: Path | None = None,
    alarm: float | None = None,
) -> dict[str, Any]:
    """The detector on ``query_sessions`` against ``map_session`` into ``out`` (SPEC 13).

    With ``rerun``, also a recording for the Rerun viewer there (:mod:`harness.detect.rerun`).

    Raises:
        ConfigError: an unknown or repeated session, the map among the queries, an unknown method.
    """
    from harness.pipeline.chain import Pipeline
    from harness.pipeline.localizer_stages import across_localizers
    from harness.runtime.executors import LocalExecutor

    opt = opt or DetectOptions()
    alarm = check_detect_args(cfg, map_session, query_sessions, opt, rerun, alarm)
    dcfg = _detect_config(cfg, map_session, query_sessions, opt)
    t0 = time.perf_counter()
    p = Pipeline(
        dcfg,
        Path(out),
        executor=executor or LocalExecutor(),
        annotations_optional=True,
        train_sessions=(map_session,),  # the model sees the map alone, never the new session
    )
    with p.locked():
        frames, ann, pairs, measured = _measure(
            p, map_session, query_sessions, opt.local_localizer()
        )
        ranks = measured[0].ranks if len(measured) == 1 else across_localizers(measured)
        names_l = [m.loc.name for m in measured]
        chunk_units = _chunk_units(ranks, frames.df, opt, dcfg)
        entries = p.units("detect", chunk_units)
        dets = pd.concat(
            [read_cached_parquet(e.path / "boxes.parquet") for e in entries], ignore_index=True
        )
        fr = pd.concat(
            [read_cached_parquet(e.path / "frames.parquet") for e in entries], ignore_index=True
        )
        al, aligned = _alignment(p.out, measured)
        record = write_outputs(
            p,
            dcfg,
            map_session,
            query_sessions,
            frames.df,
            pairs.df,
            ann.df,
            dets,
            fr,
            entries,
            opt,
            names_l,
            alarm,
            al,
        )
        record["cache_entries"] = {"detect": [e.path.name for e in entries]}
        record["thin_boxes_dropped"] = _thin_boxes(p, entries)
        record.update(aligned)
        record["kernels"] = kernels.report()
        if rerun is not None:
            record["rerun"] = write_rerun(
                Path(rerun), p.out, frames.df, map_session, fr, dets, entries, opt
            )
        if p.pairing:
            record["pairing"] = p.pairing
        record["total_s"] = round(time.perf_counter() - t0, 3)
        record["ms_per_query_frame"] = round(1000 * record["total_s"] / max(len(fr), 1), 2)
        write_json(p.out / "detect.json", record)
    return record


def _thin_boxes(p: Any, entries: list[Any]) -> int:
    """Candidates thinner than ``[detect] min_box_side``, dropped before NMS and Table D."""
    return sum(
        int(p.cache.manifest("detect", e.key)["info"].get("thin_boxes_dropped", 0)) for e in entries
    )


def _alignment(out: Path, measured: list[Any]) -> tuple[pd.DataFrame | None, dict[str, Any]]:
    """The local localizer's alignments and what ``detect.json`` says of them (SPEC 13.3).

    Returns the pairs' alignments (None without a local localizer) and the record's
    ``alignment`` (pairs by method) and ``local_counts`` (subimages ranked and dropped, by
    reason). Without one, an ``alignment.csv`` that an earlier run here recorded is removed.
    """
    al = measured[0].ranks.alignment if len(measured) == 1 else None
    if al is None:
        old = out / "detect.json"
        if old.is_file() and "alignment" in json.loads(old.read_text()):
            (out / "alignment.csv").unlink(missing_ok=True)
        return None, {}
    return al, {
        "alignment": _write_alignment(out, al),
        "local_counts": measured[0].ranks.counts.get("local", {}),
    }


def _write_alignment(out: Path, al: pd.DataFrame) -> dict[str, int]:
    """``alignment.csv`` (each pair's method, inliers and score) and its counts by method.

    A pair no link of the chain accepts is ``none``: its query frame gets no rank, so no box and
    no score (SPEC 13.3); a WARNING line counts them.
    """
    write_text(out / "alignment.csv", al.to_csv(index=False, float_format="%.6g"))
    counts = {str(k): int(v) for k, v in al["align"].value_counts().sort_index().items()}
    if counts.get("none"):
        log.warning(
            "%d of %d pairs could not be aligned: their query frames carry no change score and "
            "no box (alignment.csv lists them)",
            counts["none"],
            len(al),
        )
    return counts


def detect_pairs(
    p: Any, map_session: str, query_sessions: list[str]
) -> tuple[dict[str, Any], Any, Any, Any]:
    """Ingest, frames, annotations and the pairs by pose of the queries with the map alone."""
    from harness.pipeline.chain import until_pairs
    from harness.pipeline.context import Table

    ingested, frames, ann, pairs_all = until_pairs(p)
    sel = (pairs_all.df["r_session"] == map_session) & pairs_all.df["q_session"].isin(
        query_sessions
    )
    pairs = Table(
        pairs_all.df[sel].reset_index(drop=True),
        stable_hash("detect-pairs", pairs_all.key, map_session, sorted(query_sessions)),
    )
    if not len(pairs.df):
        raise HarnessError(
            f"detect: no frame of {query_sessions} found a map frame of {map_session} within "
            "[pairs] max_distance_m and max_yaw_diff_deg"
        )
    return ingested, frames, ann, pairs


def check_rerun_target(path: Path) -> None:
    """Refuse a ``--rerun`` path that exists and is not a recording ``harness detect`` wrote.

    Raises:
        ConfigError: the path is a folder, or a file of someone else's (never replaced).
    """
    from harness.detect.rerun import APPLICATION, rerun_sdk

    if path.is_dir():
        raise ConfigError(f"--rerun {path}: is a folder; give the .rrd file to write")
    if not path.exists():
        if not path.parent.is_dir():
            raise ConfigError(f"--rerun {path}: its folder {path.parent} does not exist")
        return
    rr = rerun_sdk()
    from rerun.chunk import RrdReader

    try:
        apps = {s.application_id for s in RrdReader(path).recordings()}
    except Exception:  # an unreadable or foreign file: not ours to replace
        apps = set()
    del rr
    if apps != {APPLICATION}:
        raise ConfigError(
            f"--rerun {path}: exists and is not a recording harness detect wrote; it is never "
            "replaced: remove it or choose another path"
        )


def write_rerun(
    path: Path,
    out: Path,
    frames: pd.DataFrame,
    map_session: str,
    fr: pd.DataFrame,
    dets: pd.DataFrame,
    entries: list[Any],
    opt: DetectOptions,
) -> dict[str, Any]:
    """The run's Rerun recording at ``path``, written beside it and moved into place whole."""
    import os

    from harness.detect.rerun import recording_id, write_recording

    check_rerun_target(path)
    fr = fr.merge(frames[[*FRAME_KEY, "x", "y", "image"]], on=FRAME_KEY)
    tmp = path.with_name(f".{path.name}.partial")
    try:
        counts = write_recording(
            tmp,
            frames,
            map_session,
            fr,
            dets,
            entries,
            recording_id(out, opt.record()),
        )
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return {"path": str(path), **counts}


def _frame_name(s: str, c: str, u: int) -> str:
    return f"{s}_{c}_{u}"


def _frame_table(
    out: Path,
    fr: pd.DataFrame,
    frames: pd.DataFrame,
    pairs: pd.DataFrame,
    names: pd.DataFrame,
    sources: dict[str, str],
    min_pair_confidence: float = 0.0,
) -> tuple[pd.DataFrame, dict[tuple[str, str, int], int]]:
    """The query frames with pose, image and map frame, numbered; ``images.json`` (COCO).

    Frames read from folders keep their file names (SPEC 13.2): ``name`` (the query image's)
    and ``r_name`` (its map image's) columns, and the COCO ``file_name`` (with ``path``, the
    file itself); a log's frame keeps the stored image as its ``file_name``. Pairs not made by
    pose carry their ``pair_confidence``, and ``uncertain_pair`` where it is below
    ``min_pair_confidence``.

    Returns the frames and the COCO image id of each frame key.
    """
    fr = fr.merge(frames[[*FRAME_KEY, "x", "y", "yaw", "image", "width", "height"]], on=FRAME_KEY)
    extra = [c for c in PAIR_EXTRA[:1] if c in pairs.columns]
    fr = fr.merge(
        pairs[[*QUERY_KEY, "r_camera", "r_utime", *extra]].rename(
            columns={"q_session": "session", "q_camera": "camera", "q_utime": "utime"}
        ),
        on=FRAME_KEY,
        how="left",
    )
    if "pair_confidence" in fr.columns:
        fr["uncertain_pair"] = fr["pair_confidence"].to_numpy(np.float64) < min_pair_confidence
    if len(names):
        fr = with_names(fr, names, FRAME_KEY, "name")
        fr = with_names(fr, names, ["r_session", "r_camera", "r_utime"], "r_name")
    fr = fr.sort_values(FRAME_KEY).reset_index(drop=True)
    fr.insert(0, "image_id", np.arange(1, len(fr) + 1))
    ids = {(s, c, int(u)): int(i) for i, s, c, u in fr[["image_id", *FRAME_KEY]].to_numpy()}
    images = [
        {
            "id": int(r.image_id),
            "file_name": getattr(r, "name", "") or str(r.image).split("#")[0],
            **(
                {"path": str(Path(sources[str(r.session)]) / str(r.name))}
                if getattr(r, "name", "")
                else {}
            ),
            "width": int(r.width),
            "height": int(r.height),
            "session": str(r.session),
            "camera": str(r.camera),
            "utime": int(r.utime),
            "rotation": str(r.image).split("#rot=")[1] if "#rot=" in str(r.image) else "none",
        }
        for r in fr.itertuples()
    ]
    write_json(
        out / "images.json",
        {"images": images, "categories": [{"id": 1, "name": "change", "supercategory": "change"}]},
    )
    return fr, ids


def _calibrated(
    fr: pd.DataFrame, dets: pd.DataFrame, entries: list[Any]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Calibrated scores (SPEC 13.1), in ``exceedance`` columns.

    Each box against every candidate box of the run, each frame against every frame, one chunk's
    candidates at a time.
    """
    from harness.detect.calibrate import exceedance

    null = np.concatenate(
        [read_cached_parquet(e.path / "candidates.parquet")["loc"].to_numpy() for e in entries]
        or [np.zeros(0)]
    )
    dets = dets.assign(
        exceedance=np.where(
            dets["kind"] == "detection", exceedance(null, dets["score"].to_numpy()), np.nan
        )
    )
    fr = fr.assign(exceedance=exceedance(fr["score"].to_numpy(), fr["score"].to_numpy()))
    return fr, dets


def _coco_results(det: pd.DataFrame, ids: dict[tuple[str, str, int], int]) -> list[dict]:
    """The change boxes as COCO results (``detections.json``), with their calibrated scores."""
    return [
        {
            "image_id": ids[(str(r.session), str(r.camera), int(r.utime))],
            "category_id": 1,
            "bbox": [float(r.x1), float(r.y1), float(r.x2 - r.x1), float(r.y2 - r.y1)],
            "score": float(r.score),
            "exceedance": float(r.exceedance),
        }
        for r in det.itertuples()
    ]


def _write_alarms(
    out: Path, fr: pd.DataFrame, det: pd.DataFrame, alarm: float
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``alarms.csv``: the frames and boxes flagged at the nominal false-alarm rate ``alarm``."""
    flagged_f = fr[fr["exceedance"] <= alarm]
    flagged_b = det[det["exceedance"] <= alarm]
    alarms = pd.concat(
        [
            flagged_f.assign(kind="frame")[["kind", *FRAME_KEY, "score", "exceedance"]],
            flagged_b.assign(kind="box")[
                ["kind", *FRAME_KEY, "x1", "y1", "x2", "y2", "score", "exceedance"]
            ],
        ],
        ignore_index=True,
    ).sort_values(["kind", "exceedance", *FRAME_KEY, "x1", "y1"], kind="stable")
    write_text(out / "alarms.csv", alarms.to_csv(index=False, float_format="%.6g"))
    return flagged_f, flagged_b


def _table_d(
    out: Path,
    cfg: Config,
    fr: pd.DataFrame,
    ann: pd.DataFrame,
    dets: pd.DataFrame,
    ids: dict[tuple[str, str, int], int],
    entries: list[Any],
    opt: DetectOptions,
    alarm: float,
) -> pd.DataFrame:
    """Table D on the annotated frames, from the candidates of those frames only."""
    from harness.detect.evaluate import score_detections

    annotated = pd.MultiIndex.from_frame(ann[FRAME_KEY].drop_duplicates())
    cands = []
    for e in entries:  # candidates of the annotated frames only, one chunk at a time
        sm = read_cached_parquet(e.path / "candidates.parquet")  # the generator's boxes
        cands.append(sm[pd.MultiIndex.from_frame(sm[QUERY_KEY]).isin(annotated)])
    return score_detections(
        out,
        fr,
        ann,
        dets,
        ids,
        pd.concat(cands, ignore_index=True),
        partial(_nms, nms_iou=opt.nms_iou, max_boxes=opt.max_boxes),
        cfg.report.chance_draws,
        cfg.report.bootstrap,
        cfg.report.ci,
        cfg.seed,
        opt.boxes,
        alarm,
        cfg.report.min_positive_images,
    )


#: ``detect.json``'s ``alarm``: the nominal rate, the frames and boxes it flags, of how many.
ALARM_FIELDS = ("rate", "frames", "boxes", "of_frames", "of_boxes")


def _frame_columns(fr: pd.DataFrame) -> list[str]:
    """The columns of ``frames.parquet`` / ``frames.csv``.

    With file names and pair confidence where the frames have them (SPEC 13.2).
    """
    named = [c for c in ("name", "r_name", *PAIR_EXTRA) if c in fr.columns]
    where = ["x", "y", "yaw", "r_session", "r_camera", "r_utime"]
    return ["image_id", *FRAME_KEY, *where, *named, *FRAME_RESULT, "exceedance"]


def write_outputs(
    p: Any,
    cfg: Config,
    map_session: str,
    queries: list[str],
    frames: pd.DataFrame,
    pairs: pd.DataFrame,
    ann: pd.DataFrame,
    dets: pd.DataFrame,
    fr: pd.DataFrame,
    entries: list[Any],
    opt: DetectOptions,
    localizers: list[str],
    alarm: float = 0.01,
    alignment: pd.DataFrame | None = None,
) -> dict[str, Any]:
    """COCO files, the frame table, LoC maps of the most changed frames, the map, Table D, page.

    Also the alarms at the nominal false-alarm rate ``alarm`` (``alarms.csv``, SPEC 13.1).
    """
    out = p.out
    names = session_names(cfg.sessions)
    sources = {sc.name: sc.source for sc in cfg.sessions}
    fr, ids = _frame_table(out, fr, frames, pairs, names, sources, cfg.pairs.min_pair_confidence)
    fr, dets = _calibrated(fr, dets, entries)
    det = dets[dets["kind"] == "detection"]
    results = _coco_results(det, ids)
    write_text(out / "detections.json", json.dumps(results))
    table = fr[_frame_columns(fr)]
    write_parquet(out / "frames.parquet", table)
    write_text(out / "frames.csv", table.to_csv(index=False, float_format="%.6g"))
    flagged_f, flagged_b = _write_alarms(out, fr, det, alarm)
    fr["alarmed"] = fr["exceedance"].to_numpy(np.float64) <= alarm  # the page's, SPEC 13.1
    sure = ~fr["uncertain_pair"] if "uncertain_pair" in fr.columns else np.ones(len(fr), bool)
    top = fr[sure].sort_values(["score", "image_id"], ascending=[False, True]).head(opt.top)
    maps = locmaps(out, top, entries, dets)
    from harness.detect.page import trajectory_figure

    traj = trajectory_figure(out / "trajectory.png", frames, map_session, fr, top)
    table_d = _table_d(out, cfg, fr, ann, dets, ids, entries, opt, alarm) if len(ann) else None
    pixel = write_pixel_table(out, cfg, names, map_session, entries, fr)
    from harness.detect.page import write_detect_page

    page = write_detect_page(
        out, fr, top, dets, frames, maps, (table_d, pixel), map_session, localizers, ann,
        alignment,
    )  # fmt: skip
    return {
        "config": cfg.name,
        "map": map_session,
        "queries": queries,
        "localizers": localizers,
        "fused_across": ALL_LOCALIZERS if len(localizers) > 1 else None,
        "options": opt.record(),
        "query_frames": len(fr),
        # SPEC 13.2: pairs under [pairs] min_pair_confidence, left out of the most-changed list
        "uncertain_pairs": int((~sure).sum()),
        "min_pair_confidence": cfg.pairs.min_pair_confidence,
        "detections": len(results),
        # SPEC 13.1: what the nominal false-alarm rate flags (alarms.csv)
        "alarm": dict(
            zip(ALARM_FIELDS, (alarm, *map(len, (flagged_f, flagged_b, fr, det))), strict=True)
        ),
        "outputs": {
            "detections": str(out / "detections.json"),
            "images": str(out / "images.json"),
            "frames": str(out / "frames.parquet"),
            "trajectory": str(traj),
            "page": str(page),
            "locmaps": [str(m) for m in maps.values()],
        },
        "table_d": table_d.to_dict(orient="records") if table_d is not None else None,
        # SPEC 13.2: the LoC maps' pixel AP against the masks (tableD_pixel.csv)
        "table_d_pixel": pixel.to_dict(orient="records") if pixel is not None else None,
        "stage_units_run": p.ran,
        "timings_s": {k: round(v, 3) for k, v in p.timings.items()},
    }


def locmaps(
    out: Path, top: pd.DataFrame, entries: list[Any], dets: pd.DataFrame
) -> dict[tuple[str, str, int], Path]:
    """LoC maps of the ``top`` frames: float16 ``.npy`` and a colour overlay with its bar."""
    from harness.reports.overlay import colour_bar

    want = set(map(tuple, top[FRAME_KEY].to_numpy().tolist()))
    d = out / "locmaps"
    d.mkdir(exist_ok=True)
    written: dict[tuple[str, str, int], Path] = {}
    for e in entries:
        s = read_cached_parquet(e.path / "samples.parquet")
        for key, g in s.groupby(QUERY_KEY, sort=True):
            k = (str(key[0]), str(key[1]), int(key[2]))
            if k not in want:
                continue
            r = top[(top["session"] == k[0]) & (top["camera"] == k[1]) & (top["utime"] == k[2])]
            img = read_image(str(r["image"].iloc[0]))
            h, w = img.shape[:2]
            m = loc_map(
                g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64),
                g["loc"].to_numpy(np.float64),
                w,
                h,
            )
            name = _frame_name(*k)
            np.save(d / f"{name}.npy", m.astype(np.float16))
            lo, hi = float(np.nanmin(m)), float(np.nanmax(m))
            norm = np.nan_to_num((m - lo) / (hi - lo) if hi > lo else np.zeros_like(m))
            heat = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]
            over = (0.45 * img + 0.55 * heat).astype(np.uint8)
            over[~np.isfinite(m)] = img[~np.isfinite(m)]
            b = dets[
                (dets["kind"] == "detection")
                & (dets["session"] == k[0])
                & (dets["camera"] == k[1])
                & (dets["utime"] == k[2])
            ]
            for x1, y1, x2, y2 in b[["x1", "y1", "x2", "y2"]].to_numpy():
                cv2.rectangle(
                    over, (int(x1), int(y1)), (int(x2) - 1, int(y2) - 1), (0, 255, 255), 1
                )
            up = max(1, int(np.ceil(240 / w)))  # small frames: enlarged so the bar is legible
            big = cv2.resize(over, (w * up, h * up), interpolation=cv2.INTER_NEAREST)
            panel = np.vstack([big, colour_bar(w * up, lo, hi)])
            cv2.imwrite(str(d / f"{name}.png"), panel[..., ::-1])
            written[k] = d / f"{name}.png"
    return written

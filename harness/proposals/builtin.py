"""The built-in proposers (method §5): ``grid5`` and OpenCV's ``mser``, ``segments``, ``edges``...

... and ``selective`` (Selective Search, from OpenCV's contrib modules).

``grid5`` gives the paper's five fixed boxes; the others need no weights. :func:`nms` is the
non-maximum suppression every proposer uses.
"""

from __future__ import annotations

import ctypes
import functools
import threading
from typing import Any

import cv2
import numpy as np

from harness.boxes import nms
from harness.methods import proposer
from harness.proposals.config import (
    EdgesConfig,
    MserConfig,
    ProposalsConfig,
    SegmentsConfig,
    SelectiveConfig,
)


@proposer("full")
def full_frame(width: float, height: float) -> np.ndarray:
    """The whole frame as one box: what a place descriptor describes (pairing by sequence)."""
    return np.array([[0.0, 0.0, float(width), float(height)]])


@proposer("grid5")
def grid5(width: float, height: float) -> np.ndarray:
    """The five fixed boxes of method §5 as a (5, 4) float array ``x1, y1, x2, y2``."""
    w, h = float(width), float(height)
    return np.array(
        [
            [w / 3, h / 3, 2 * w / 3, 2 * h / 3],
            [0.0, 0.0, 2 * w / 3, 2 * h / 3],
            [w / 3, 0.0, w, 2 * h / 3],
            [0.0, h / 3, 2 * w / 3, h],
            [w / 3, h / 3, w, h],
        ],
        dtype=np.float64,
    )


def working_copy(rgb: np.ndarray, work_width: int) -> tuple[np.ndarray, float]:
    """``rgb`` shrunk to at most ``work_width`` pixels wide (area interpolation), and the scale."""
    h, w = rgb.shape[:2]
    scale = min(1.0, work_width / w)
    if scale >= 1:
        return rgb, scale
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), scale


def mser_boxes(rgb: np.ndarray, cfg: MserConfig) -> tuple[np.ndarray, np.ndarray]:
    """MSER region boxes in full-image pixels, scored by their area fraction; (k, 4), (k,)."""
    h, w = rgb.shape[:2]
    small, scale = working_copy(rgb, cfg.work_width)
    gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    sa = gray.shape[0] * gray.shape[1]
    mser = cv2.MSER_create(  # type: ignore[attr-defined]  # not in OpenCV's stubs
        5, max(8, int(cfg.min_area_frac * sa * 0.3)), int(cfg.max_area_frac * sa)
    )
    _, bb = mser.detectRegions(gray)
    if len(bb) == 0:
        return np.zeros((0, 4)), np.zeros(0)
    bb = np.asarray(bb, np.float64).reshape(-1, 4) / scale
    boxes = np.column_stack([bb[:, 0], bb[:, 1], bb[:, 0] + bb[:, 2], bb[:, 1] + bb[:, 3]])
    boxes = np.clip(boxes, 0, [w, h, w, h])
    frac = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]) / (w * h)
    ok = (frac >= cfg.min_area_frac) & (frac <= cfg.max_area_frac)
    boxes, frac = np.round(boxes[ok], 2), frac[ok]
    boxes, idx = np.unique(boxes, axis=0, return_index=True)
    frac = frac[idx]
    keep = nms(boxes, frac, cfg.nms_iou)[: cfg.max_boxes]
    return boxes[keep], frac[keep]


def segment_boxes(rgb: np.ndarray, cfg: SegmentsConfig) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of colour regions in full-image pixels, scored by their area fraction; (k, 4), (k,).

    The pixels of a copy ``work_width`` wide (CIELAB, lightly blurred) fall into ``cfg.k`` colour
    clusters by faiss k-means (seeded); each cluster's mask, closed with each kernel of
    ``cfg.closings`` so that the cells of a textured object merge, gives the bounding boxes of its
    8-connected regions (``cv2.connectedComponentsWithStats``). A new object of its own colours
    is a region of its own, whatever the edges of the scene around it.
    """
    import faiss

    h, w = rgb.shape[:2]
    small, scale = working_copy(rgb, cfg.work_width)
    lab = cv2.cvtColor(cv2.GaussianBlur(small, (0, 0), 0.8), cv2.COLOR_RGB2Lab)
    px = np.ascontiguousarray(lab.reshape(-1, 3), np.float32)
    k = max(1, min(cfg.k, len(px) // 39))  # faiss wants 39 points per centroid
    km = faiss.Kmeans(3, k, niter=20, seed=cfg.seed, verbose=False)
    km.train(px)
    labels = km.index.search(px, 1)[1].reshape(lab.shape[:2])
    area = float(lab.shape[0] * lab.shape[1])
    found = []
    for c in range(k):
        mask = (labels == c).astype(np.uint8)
        for size in cfg.closings:
            m = (
                mask
                if size <= 1
                else cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((size, size), np.uint8))
            )
            n, _, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
            found.append(stats[1:n, :4])
    bb = np.unique(np.concatenate(found).astype(np.float64).reshape(-1, 4), axis=0)
    frac = bb[:, 2] * bb[:, 3] / area
    bb = bb[(frac >= cfg.min_area_frac) & (frac <= cfg.max_area_frac)]
    if not len(bb):
        return np.zeros((0, 4)), np.zeros(0)
    boxes = np.column_stack([bb[:, 0], bb[:, 1], bb[:, 0] + bb[:, 2], bb[:, 1] + bb[:, 3]])
    boxes = np.clip(np.round(boxes / scale, 2), 0, [w, h, w, h])
    frac = bb[:, 2] * bb[:, 3] / area
    keep = nms(boxes, frac, cfg.nms_iou)[: cfg.max_boxes]
    return boxes[keep], frac[keep]


def edge_boxes(rgb: np.ndarray, cfg: EdgesConfig) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of closed edge contours at several dilation scales, scored by edge density.

    Returns boxes (k, 4) and scores (k,).

    Canny thresholds follow the image's median grey level; each dilation size merges nearby
    edges into larger contours, so one image gives parts and whole objects alike.
    """
    h, w = rgb.shape[:2]
    small, scale = working_copy(rgb, cfg.work_width)
    gray = cv2.GaussianBlur(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), (0, 0), 1.0)
    med = float(np.median(gray))
    edges = cv2.Canny(gray, int(0.33 * med), int(0.66 * med) + 1)
    found = []
    for k in cfg.dilations:
        d = cv2.dilate(edges, np.ones((k, k), np.uint8)) if k > 1 else edges
        contours, _ = cv2.findContours(d, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        found += [cv2.boundingRect(c) for c in contours]
    if not found:
        return np.zeros((0, 4)), np.zeros(0)
    bb = np.unique(np.asarray(found, np.int64).reshape(-1, 4), axis=0)
    x1, y1, x2, y2 = bb[:, 0], bb[:, 1], bb[:, 0] + bb[:, 2], bb[:, 1] + bb[:, 3]
    frac = (x2 - x1) * (y2 - y1) / float(gray.shape[0] * gray.shape[1])
    ok = (frac >= cfg.min_area_frac) & (frac <= cfg.max_area_frac)
    x1, y1, x2, y2 = x1[ok], y1[ok], x2[ok], y2[ok]
    if not len(x1):
        return np.zeros((0, 4)), np.zeros(0)
    ii = cv2.integral((edges > 0).astype(np.uint8)).astype(np.float64)
    density = (ii[y2, x2] - ii[y1, x2] - ii[y2, x1] + ii[y1, x1]) / ((x2 - x1) * (y2 - y1))
    boxes = np.clip(np.column_stack([x1, y1, x2, y2]) / scale, 0, [w, h, w, h]).astype(np.float64)
    keep = nms(boxes, density, cfg.nms_iou)[: cfg.max_boxes]
    return boxes[keep], density[keep]


@proposer("edges")
def edges_proposer(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    """``edges`` with ``[proposals.edges]``."""
    return edge_boxes(rgb, cfg.edges)


@proposer("mser")
def mser_proposer(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    """``mser`` with ``[proposals.mser]``."""
    return mser_boxes(rgb, cfg.mser)


@proposer("segments")
def segments_proposer(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    """``segments`` with ``[proposals.segments]``."""
    return segment_boxes(rgb, cfg.segments)


_RAND_LOCK = threading.Lock()


@functools.cache
def _libc() -> ctypes.CDLL:
    """The C library OpenCV's rand() comes from (this process's)."""
    return ctypes.CDLL(None)


def selective_rects(bgr: np.ndarray, mode: str, seed: int) -> np.ndarray:
    """OpenCV's Selective Search on one BGR working copy: its (k, 4) x, y, w, h rects.

    One thread, the C library's generator seeded with ``seed`` first (under a lock: that state is
    the process's), so the same copy gives the same rects in the same order in any process.
    """
    ss = cv2.ximgproc.segmentation.createSelectiveSearchSegmentation()
    ss.setBaseImage(bgr)
    if mode == "quality":
        ss.switchToSelectiveSearchQuality()
    else:
        ss.switchToSelectiveSearchFast()
    with _RAND_LOCK:
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            _libc().srand(seed)
            return np.asarray(ss.process(), np.float64).reshape(-1, 4)
        finally:
            cv2.setNumThreads(threads)


def selective_boxes(
    rgb: np.ndarray, cfg: SelectiveConfig, workers: Any = None
) -> tuple[np.ndarray, np.ndarray]:
    """Selective Search's boxes in full-image pixels, scored by their order; (k, 4), (k,).

    OpenCV's ``ximgproc.segmentation.createSelectiveSearchSegmentation`` on a copy
    ``work_width`` wide (:func:`selective_rects`; in one of ``workers``'
    processes where given, :class:`harness.runtime.workers.Workers`), then the area limits,
    near-duplicates merged by NMS in Selective Search's order, the first ``max_boxes`` kept.
    """
    h, w = rgb.shape[:2]
    small, scale = working_copy(rgb, cfg.work_width)
    bgr = cv2.cvtColor(small, cv2.COLOR_RGB2BGR)
    if workers is None:
        rects = selective_rects(bgr, cfg.mode, cfg.seed)
    else:
        rects = workers.call(selective_rects, bgr, cfg.mode, cfg.seed)
    if not len(rects):
        return np.zeros((0, 4)), np.zeros(0)
    frac = rects[:, 2] * rects[:, 3] / float(small.shape[0] * small.shape[1])
    rects = rects[(frac >= cfg.min_area_frac) & (frac <= cfg.max_area_frac)]
    boxes = np.column_stack([rects[:, :2], rects[:, :2] + rects[:, 2:]]) / scale
    boxes = np.clip(boxes, 0, [w, h, w, h])
    order = 1.0 - np.arange(len(boxes)) / max(1, len(boxes))  # Selective Search's first: 1
    keep = nms(boxes, order, cfg.nms_iou)[: cfg.max_boxes]
    return boxes[keep], order[keep]


@proposer("selective")
def selective_proposer(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    """``selective`` with ``[proposals.selective]``."""
    return selective_boxes(rgb, cfg.selective)

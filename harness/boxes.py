"""Boxes (x1, y1, x2, y2): intersection over union and greedy non-maximum suppression.

One home for both. :func:`iou_matrix` computes IoU as the library a result must agree with
computes it (COCO's evaluation, or OpenCV's ``Rect2d``). The NMS is OpenCV's greedy
``dnn.NMSBoxes``: :func:`nms` calls it, for a box set scored once (proposals, YOLO);
:func:`greedy_nms` is the same suppression on an overlap matrix made once, for a box set scored
many times (a detect chunk's boxes and their random row, Table D's chance draws:
:class:`FrameNMS`); ``tests/detect/test_nms.py`` holds the two equal, box for box. OpenCV is the
faster for one scoring (0.8 ms against 4.5 ms at 300 boxes, 69 ms against 1.7 s at 3,000), the
matrix for hundreds of scorings.
"""

from __future__ import annotations

import cv2
import numpy as np


def iou_matrix(a: np.ndarray, b: np.ndarray, opencv: bool = False) -> np.ndarray:
    """IoU of every box of ``a`` (n, 4: x1 y1 x2 y2) with every box of ``b`` (m, 4).

    The arithmetic of the library a result must agree with: COCO's (pycocotools; 0 where the union
    is empty), or with ``opencv`` OpenCV's ``Rect2d`` overlap, which ``dnn.NMSBoxes`` thresholds:
    each box as (x, y, x2 - x1, y2 - y1), its far corner x + w again, and 1 where both boxes have
    no area (its ``jaccardDistance`` is 0 there).
    """
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    if not len(a) or not len(b):
        return np.zeros((len(a), len(b)))
    if opencv:
        return 1.0 - _jaccard_distance(a, b)
    iw = np.clip(
        np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None
    )
    ih = np.clip(
        np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None
    )
    inter = iw * ih
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def _jaccard_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """OpenCV's ``jaccardDistance`` of ``Rect2d`` boxes, in doubles (see :func:`iou_matrix`)."""
    wa, ha, wb, hb = a[:, 2] - a[:, 0], a[:, 3] - a[:, 1], b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    iw = np.minimum((a[:, 0] + wa)[:, None], (b[:, 0] + wb)[None, :]) - np.maximum(
        a[:, 0][:, None], b[:, 0][None, :]
    )
    ih = np.minimum((a[:, 1] + ha)[:, None], (b[:, 1] + hb)[None, :]) - np.maximum(
        a[:, 1][:, None], b[:, 1][None, :]
    )
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    tot = (wa * ha)[:, None] + (wb * hb)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(tot <= np.finfo(np.float64).eps, 0.0, 1.0 - inter / (tot - inter))


def suppression(boxes: np.ndarray, nms_iou: float) -> np.ndarray:
    """(n, n) bool: which box suppresses which in greedy NMS at ``nms_iou`` (symmetric).

    OpenCV's ``dnn.NMSBoxes`` overlap exactly: each (x1, y1, x2, y2) box as a ``Rect2d`` (x, y,
    x2 - x1, y2 - y1), their intersection over union in doubles (0 where both areas are 0), taken
    to float32 as OpenCV's ``1 - jaccardDistance``, and compared with the threshold as float32.
    """
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    if not len(b):
        return np.zeros((0, 0), bool)
    dist = _jaccard_distance(b, b)  # iou_matrix's OpenCV arithmetic, as a distance
    overlap = np.float32(1.0) - dist.astype(np.float32)
    return overlap > np.float32(nms_iou)


def nms(
    boxes: np.ndarray, scores: np.ndarray, iou: float, classes: np.ndarray | None = None
) -> np.ndarray:
    """Indices kept by (class-aware) non-maximum suppression, highest score first; ties by index."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    xywh = np.column_stack(
        [boxes[:, 0], boxes[:, 1], boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]]
    )
    cls = np.zeros(len(boxes), np.int32) if classes is None else classes.astype(np.int32)
    kept = cv2.dnn.NMSBoxesBatched(
        xywh.tolist(), scores.astype(float).tolist(), cls.tolist(), -1e9, float(iou)
    )
    keep = np.asarray(kept, np.int64).ravel()
    order = np.lexsort((keep, -scores[keep]))
    return keep[order]


def greedy_nms(
    boxes: np.ndarray,
    loc: np.ndarray,
    nms_iou: float,
    max_boxes: int,
    suppress: np.ndarray | None = None,
) -> np.ndarray:
    """Indices of the kept boxes: by descending score, greedy NMS at ``nms_iou``, ``max_boxes``.

    The boxes OpenCV's ``dnn.NMSBoxes`` keeps on (x, y, w, h), its first ``max_boxes``
    (tests/detect/test_nms.py compares the two), found without testing the boxes after them;
    boxes without a finite LoC never enter; ties: the earlier box first. ``suppress``:
    :func:`suppression` of these boxes where it was made before (a frame scored many times).
    """
    ok = np.isfinite(loc)
    if not ok.any():
        return np.zeros(0, np.int64)
    sup = suppression(boxes, nms_iou) if suppress is None else suppress
    idx = np.flatnonzero(ok)
    order = idx[np.argsort(-loc[idx], kind="stable")]
    alive = ok.copy()
    kept: list[int] = []
    pos = 0
    while len(kept) < max_boxes and pos < len(order):
        live = alive[order[pos:]]
        j = int(np.argmax(live))
        if not live[j]:
            break
        i = int(order[pos + j])
        kept.append(i)
        pos += j + 1
        alive &= ~sup[i]
    return np.asarray(kept, np.int64)


class FrameNMS:
    """``greedy_nms`` as a function of (boxes, scores), each box set's suppression made once.

    Table D's chance draws score the same candidates of a frame hundreds of times.
    """

    def __init__(self, nms_iou: float, max_boxes: int) -> None:
        self.nms_iou, self.max_boxes = nms_iou, max_boxes
        self._made: dict[bytes, np.ndarray] = {}

    def __call__(self, boxes: np.ndarray, scores: np.ndarray) -> np.ndarray:
        """The kept indices of ``boxes`` under ``scores``."""
        b = np.ascontiguousarray(boxes, np.float64).reshape(-1, 4)
        key = b.tobytes()
        if key not in self._made:
            self._made[key] = suppression(b, self.nms_iou)
        return greedy_nms(b, scores, self.nms_iou, self.max_boxes, self._made[key])

    def many(self, boxes: np.ndarray, scores: np.ndarray) -> np.ndarray:
        """The kept indices of ``boxes`` under each row of ``scores`` (d, n), all finite.

        (d, ``max_boxes``) int, -1 past a row's last kept box: row by row what :meth:`__call__`
        keeps (the same stable order, the same suppression), the greedy steps taken for all rows
        at once.
        """
        b = np.ascontiguousarray(boxes, np.float64).reshape(-1, 4)
        d, n = scores.shape
        kept = np.full((d, self.max_boxes), -1, np.int64)
        if not n:
            return kept
        key = b.tobytes()
        if key not in self._made:
            self._made[key] = suppression(b, self.nms_iou)
        sup = self._made[key]
        order = np.argsort(-scores, axis=1, kind="stable")
        alive = np.ones((d, n), bool)
        rows = np.arange(d)
        for t in range(self.max_boxes):
            live = np.take_along_axis(alive, order, axis=1)
            j = np.argmax(live, axis=1)
            has = live[rows, j]
            if not has.any():
                break
            i = order[rows, j]
            kept[has, t] = i[has]
            alive[has] &= ~sup[i[has]]
            alive[rows[has], i[has]] = False
        return kept

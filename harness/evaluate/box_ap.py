"""Table D's box AP (method §13.1): pycocotools' evaluation beside the VOC all-point AP.

Matching at IoU 0.5 (the boxes' IoU is :func:`harness.boxes.iou_matrix`'s) and the exact
(Clopper-Pearson) interval of a rate.
"""

from __future__ import annotations

import contextlib
import io
from typing import Any

import numpy as np
import pandas as pd

from harness.records import CHANGE_CATEGORY, FRAME_KEY


def _voc_all_point(tp: np.ndarray, scores: np.ndarray, n_gt: int) -> float:
    """VOC all-point interpolated AP (the area under the monotone precision envelope)."""
    tp = np.asarray(tp).astype(bool)
    return weighted_voc(np.asarray(scores, np.float64), tp, np.ones(len(tp)), float(n_gt))


def weighted_voc(scores: np.ndarray, tp: np.ndarray, w: np.ndarray, n_gt: float) -> float:
    """VOC all-point AP where detection i counts ``w[i]`` times (bootstrap multiplicities)."""
    if n_gt <= 0:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    ww, t = w[order], tp[order]
    ctp, cfp = np.cumsum(ww * t), np.cumsum(ww * ~t)
    rec = ctp / n_gt
    prec = ctp / np.maximum(ctp + cfp, np.finfo(np.float64).eps)
    mrec = np.concatenate([[0.0], rec, [1.0]])
    mpre = np.maximum.accumulate(np.concatenate([[0.0], prec, [0.0]])[::-1])[::-1]
    i = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[i + 1] - mrec[i]) * mpre[i + 1]))


def coco_results(
    image_ids: Any, boxes: np.ndarray, scores: Any, **extra: Any
) -> list[dict[str, Any]]:
    """Boxes as COCO results, the one builder of ``detections.json`` and of Table D's results.

    Each result holds ``image_id``, ``category_id`` 1 (a change), ``bbox`` (x, y, w, h),
    ``score``, then each of ``extra`` (a value per box), in that order. ``boxes``: (n, 4) x1, y1,
    x2, y2 in pixels, beside ``image_ids`` and ``scores`` (n each).
    """
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    names = list(extra)
    cols = [list(extra[k]) for k in names]
    return [
        {
            "image_id": int(i),
            "category_id": CHANGE_CATEGORY["id"],
            "bbox": [float(x1), float(y1), float(x2 - x1), float(y2 - y1)],
            "score": float(s),
            **{k: v[j] for k, v in zip(names, cols, strict=True)},
        }
        for j, (i, (x1, y1, x2, y2), s) in enumerate(zip(image_ids, b, scores, strict=True))
    ]


def coco_eval(gt: dict[str, Any], dets: list[dict[str, Any]]) -> tuple[float, float, float]:
    """(VOC all-point AP at IoU 0.5, COCO AP@[.5:.95], COCO AP@.5) by pycocotools' COCOeval.

    The matching (greedy by score, crowd-free, at IoU 0.5) is COCOeval's; the all-point area is
    integrated from its per-detection matches at IoU 0.5. Frames without a change box count as
    images with no ground truth: their detections are false positives only.
    """
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    n_gt = len(gt["annotations"])
    if n_gt == 0:
        return float("nan"), float("nan"), float("nan")
    with contextlib.redirect_stdout(io.StringIO()):
        cg = COCO()
        cg.dataset = gt
        cg.createIndex()
        if not dets:
            return 0.0, 0.0, 0.0
        cd = cg.loadRes(dets)
        ev = COCOeval(cg, cd, "bbox")
        ev.params.maxDets = [1, 10, 100]
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    tps, scs = [], []
    t50 = 0  # iouThrs[0] = 0.5
    for e in ev.evalImgs:
        if e is None or e["aRng"] != ev.params.areaRng[0]:
            continue
        m = np.asarray(e["dtMatches"])[t50]
        ign = np.asarray(e["dtIgnore"])[t50].astype(bool)
        tps.append((m > 0)[~ign])
        scs.append(np.asarray(e["dtScores"])[~ign])
    tp = np.concatenate(tps) if tps else np.zeros(0)
    sc = np.concatenate(scs) if scs else np.zeros(0)
    return _voc_all_point(tp, sc, n_gt), float(ev.stats[0]), float(ev.stats[1])


def voc_at(gt: dict[str, Any], dets: list[dict[str, Any]], iou: float) -> tuple[float, np.ndarray]:
    """VOC all-point AP at one IoU threshold, and how far matched detections sit off their truth.

    COCOeval's matching (greedy by score, crowd-free) at ``iou`` alone; the all-point area as
    :func:`coco_eval` integrates it. The second value: for each detection matched at ``iou``, the
    distance in pixels between its centre and its truth box's (loose labels show as a median of
    many pixels with a tight detector).
    """
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    n_gt = len(gt["annotations"])
    if n_gt == 0:
        return float("nan"), np.zeros(0)
    if not dets:
        return 0.0, np.zeros(0)
    with contextlib.redirect_stdout(io.StringIO()):
        cg = COCO()
        cg.dataset = gt
        cg.createIndex()
        cd = cg.loadRes(dets)
        ev = COCOeval(cg, cd, "bbox")
        ev.params.iouThrs = np.array([iou])
        ev.params.maxDets = [100]
        ev.evaluate()
    tps, scs, offsets = [], [], []
    for e in ev.evalImgs:
        if e is None or e["aRng"] != ev.params.areaRng[0]:
            continue
        m = np.asarray(e["dtMatches"])[0]
        ign = np.asarray(e["dtIgnore"])[0].astype(bool)
        tps.append((m > 0)[~ign])
        scs.append(np.asarray(e["dtScores"])[~ign])
        for did, gid in zip(e["dtIds"], m, strict=True):
            if gid > 0:
                (dx, dy, dw, dh), (gx, gy, gw, gh) = cd.anns[did]["bbox"], cg.anns[int(gid)]["bbox"]
                offsets.append(np.hypot(dx + dw / 2 - gx - gw / 2, dy + dh / 2 - gy - gh / 2))
    tp = np.concatenate(tps) if tps else np.zeros(0)
    sc = np.concatenate(scs) if scs else np.zeros(0)
    return _voc_all_point(tp, sc, n_gt), np.asarray(offsets, np.float64)


def coco_ground_truth(
    fr: pd.DataFrame, ann: pd.DataFrame, ids: dict[tuple[str, str, int], int]
) -> dict[str, Any]:
    """The annotated query frames as a COCO ground truth (category 1 = change)."""
    annotated = ann[FRAME_KEY].drop_duplicates()
    keyset = {(str(s), str(c), int(u)) for s, c, u in annotated.to_numpy()}
    imgs = [
        {"id": ids[k], "width": int(w), "height": int(h)}
        for k, w, h in zip(
            map(tuple, fr[FRAME_KEY].to_numpy().tolist()), fr["width"], fr["height"], strict=True
        )
        if (str(k[0]), str(k[1]), int(k[2])) in keyset
    ]
    anns: list[dict[str, Any]] = []
    chg = ann[ann["status"] == "change"]
    for r in chg.itertuples():
        k = (str(r.session), str(r.camera), int(r.utime))
        if k not in ids:
            continue
        w, h = float(r.x2 - r.x1), float(r.y2 - r.y1)
        anns.append(
            {
                "id": len(anns) + 1,
                "image_id": ids[k],
                "category_id": CHANGE_CATEGORY["id"],
                "bbox": [float(r.x1), float(r.y1), w, h],
                "area": w * h,
                "iscrowd": 0,
            }
        )
    return {"images": imgs, "annotations": anns, "categories": [dict(CHANGE_CATEGORY)]}


def match50(iou: np.ndarray, order: np.ndarray) -> np.ndarray:
    """COCOeval's greedy matching at IoU 0.5 of one image's detections, in score order.

    Each detection (rows of ``iou``, taken in ``order``) takes the not yet matched ground-truth box
    of largest IoU >= 0.5 (the last of equals, as COCOeval's loop does). Returns the true-positive
    flag of each detection in ``order``.
    """
    taken = np.zeros(iou.shape[1], bool)
    tp = np.zeros(len(order), bool)
    for j, d in enumerate(order):
        best, m = 0.5, -1
        for g in range(iou.shape[1]):
            if taken[g] or iou[d, g] < best:
                continue
            best, m = iou[d, g], g
        if m >= 0:
            taken[m] = tp[j] = True
    return tp


def match50_rows(iou: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """:func:`match50` of many detection sets of one image at once.

    ``iou``: (n, g) of the image's candidates with its ground truth; ``kept``: (d, k) each set's
    detections in score order as candidate indices, -1 where a set has fewer. Returns (d, k)
    true-positive flags: row by row what :func:`match50` gives (the last of equal IoUs).
    """
    d, k = kept.shape
    g = iou.shape[1]
    tp = np.zeros((d, k), bool)
    if not g or not len(iou):
        return tp
    rows = np.arange(d)
    taken = np.zeros((d, g), bool)
    for j in range(k):
        valid = kept[:, j] >= 0
        vals = np.where(taken | ~valid[:, None], -np.inf, iou[np.maximum(kept[:, j], 0)])
        last = g - 1 - np.argmax(vals[:, ::-1], axis=1)  # the last of the largest
        hit = vals[rows, last] >= 0.5
        taken[rows[hit], last[hit]] = True
        tp[:, j] = hit
    return tp


def clopper_pearson(k: int, n: int, ci: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) interval of a rate of ``k`` in ``n`` at level ``ci``.

    The beta quantiles by ``scipy.special.betaincinv``: ``scipy.stats.beta.ppf``'s values (the
    same bits on every count up to 5,000, tested) without importing ``scipy.stats``, which costs
    a run 0.6 s.
    """
    from scipy.special import betaincinv

    if n == 0:
        return float("nan"), float("nan")
    a = (1.0 - ci) / 2.0
    lo = 0.0 if k == 0 else float(betaincinv(k, n - k + 1, a))
    hi = 1.0 if k == n else float(betaincinv(k + 1, n - k, 1.0 - a))
    return lo, hi

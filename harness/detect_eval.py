"""Table D (SPEC 13): ``harness detect``'s change boxes scored on the annotated query frames.

pycocotools' COCOeval does the matching; COCO AP@[.5:.95] and AP@.5 are its statistics, and the
AP at IoU 0.5 with VOC all-point interpolation (the metric of "The Change You Want to See", WACV
2023) is integrated from its matches. The floor row is the same fused qBBs with random scores.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .cache import write_json, write_text

FRAME_KEY = ["session", "camera", "utime"]


def _voc_all_point(tp: np.ndarray, scores: np.ndarray, n_gt: int) -> float:
    """VOC all-point interpolated AP (the area under the monotone precision envelope)."""
    if n_gt == 0:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    tp = tp[order].astype(np.float64)
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    rec = ctp / n_gt
    prec = ctp / np.maximum(ctp + cfp, np.finfo(np.float64).eps)
    mrec = np.concatenate([[0.0], rec, [1.0]])
    mpre = np.concatenate([[0.0], prec, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    i = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[i + 1] - mrec[i]) * mpre[i + 1]))


def coco_eval(gt: dict[str, Any], dets: list[dict[str, Any]]) -> tuple[float, float, float]:
    """(VOC all-point AP at IoU 0.5, COCO AP@[.5:.95], COCO AP@.5) by pycocotools' COCOeval.

    The matching (greedy by score, crowd-free, at IoU 0.5) is COCOeval's; the all-point area is
    integrated from its per-detection matches at IoU 0.5. Frames without a change box count as
    images with no ground truth: their detections are false positives only.
    """
    import contextlib
    import io

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


def coco_ground_truth(
    fr: pd.DataFrame, ann: pd.DataFrame, ids: dict[tuple[str, str, int], int]
) -> dict[str, Any]:
    """The annotated query frames as a COCO ground truth (category 1 = change)."""
    annotated = ann[["session", "camera", "utime"]].drop_duplicates()
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
                "category_id": 1,
                "bbox": [float(r.x1), float(r.y1), w, h],
                "area": w * h,
                "iscrowd": 0,
            }
        )
    return {"images": imgs, "annotations": anns, "categories": [{"id": 1, "name": "change"}]}


def score_detections(
    out: Path,
    fr: pd.DataFrame,
    ann: pd.DataFrame,
    dets: pd.DataFrame,
    ids: dict[tuple[str, str, int], int],
) -> pd.DataFrame | None:
    """Table D: the detector's box APs on the annotated query frames, beside the random floor."""
    gt = coco_ground_truth(fr, ann, ids)
    if not gt["images"]:
        return None
    on = {i["id"] for i in gt["images"]}
    write_json(out / "ground_truth.json", gt)
    rows = []
    for kind, label in (("detection", "detector"), ("random", "floor: random scores, same boxes")):
        d = dets[dets["kind"] == kind]
        res = [
            {
                "image_id": ids[k],
                "category_id": 1,
                "score": float(s),
                "bbox": [float(x1), float(y1), float(x2 - x1), float(y2 - y1)],
            }
            for k, x1, y1, x2, y2, s in zip(
                map(tuple, d[FRAME_KEY].to_numpy().tolist()),
                d["x1"],
                d["y1"],
                d["x2"],
                d["y2"],
                d["score"],
                strict=True,
            )
            if ids.get((str(k[0]), str(k[1]), int(k[2]))) in on
        ]
        voc, coco, coco50 = coco_eval(gt, res)
        rows.append(
            {
                "row": label,
                "ap50_voc_all_point": voc,
                "coco_ap_50_95": coco,
                "coco_ap_50": coco50,
                "annotated_frames": len(gt["images"]),
                "change_boxes": len(gt["annotations"]),
                "detections": len(res),
            }
        )
    t = pd.DataFrame(rows)
    write_text(out / "tableD.csv", t.to_csv(index=False, float_format="%.4f"))
    write_text(out / "tableD.md", table_d_markdown(t))
    return t


def table_d_markdown(t: pd.DataFrame) -> str:
    """Table D as markdown, with what each column measures."""
    lines = [
        "# Table D: change boxes on the annotated query frames",
        "",
        "Box AP of the detector's change boxes (SPEC 13) against the annotated change boxes, by "
        "pycocotools' COCOeval: AP at IoU 0.5 with VOC all-point interpolation (the metric of "
        "'The Change You Want to See', WACV 2023), COCO AP@[.5:.95] and COCO AP@.5 (101-point). "
        "Frames annotated no-change contribute false positives only. Floor: the same fused qBBs "
        "with random scores, through the same NMS.",
        "",
        "| | AP50 (VOC all-point) | COCO AP@[.5:.95] | COCO AP@.5 | frames | change boxes | "
        "detections |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in t.itertuples():
        lines.append(
            f"| {r.row} | {r.ap50_voc_all_point:.3f} | {r.coco_ap_50_95:.3f} | "
            f"{r.coco_ap_50:.3f} | {r.annotated_frames} | {r.change_boxes} | {r.detections} |"
        )
    from .detect_page import table_d_warnings

    lines += ["", *table_d_warnings(t)]
    return "\n".join(lines) + "\n"

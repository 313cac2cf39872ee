"""Table D (method §13): ``harness detect``'s change boxes scored on the annotated query frames.

pycocotools' COCOeval does the matching (:mod:`harness.detect.ap`); COCO AP@[.5:.95] and AP@.5
are its statistics, and the AP at IoU 0.5 with VOC all-point interpolation (the metric of "The
Change You Want to See", WACV 2023) is integrated from its matches.

method §9 for Table D (:func:`table_d_chance`): the floor is the mean AP50 of ``[report]
chance_draws`` draws of random scores on the same candidate boxes (the fused qBBs of every
annotated frame) through the same NMS, the chance band the draws' 5th-95th percentiles; the ceiling
the same candidates scored by their best IoU with an annotated change box, through the same NMS;
the candidates' recall is the share of annotated change boxes that some candidate meets at IoU 0.5.
The draws are matched by :func:`harness.detect.ap.match50`, COCOeval's greedy matching at IoU 0.5
(tested equal to pycocotools on the run's own detections), so that 200 draws cost seconds, not 200
COCOevals.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.detect.ap import (
    clopper_pearson,
    coco_eval,
    coco_ground_truth,
    iou_matrix,
    match50,
    weighted_voc,
)
from harness.detect.difference import PIXEL_BASELINES, difference_dets
from harness.detect.table import table_d_markdown
from harness.evaluate import chance
from harness.evaluate.metrics import interval, resample_counts
from harness.records import FRAME_KEY, QUERY_KEY
from harness.runtime.cache import write_json, write_text


def _frame_dets(
    boxes: np.ndarray, scores: np.ndarray, gt: np.ndarray, nms: Any
) -> tuple[np.ndarray, np.ndarray]:
    """(scores, true-positive flags) of one frame's detections: ``nms`` keeps, COCO matches."""
    keep = np.asarray(nms(boxes, scores), np.int64)
    if not len(keep):
        return np.zeros(0), np.zeros(0, bool)
    sc = scores[keep]
    order = np.argsort(-sc, kind="stable")
    tp = np.zeros(len(keep), bool)
    tp[order] = match50(iou_matrix(boxes[keep], gt), order)
    return sc, tp


def _random_score_aps(
    cands: dict[int, np.ndarray],
    gts: dict[int, np.ndarray],
    nms: Any,
    ids: list[int],
    n_gt: int,
    draws: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """AP50 of ``draws`` random scorings of the candidates, through the detector's NMS."""
    aps = np.empty(draws)
    for b in range(draws):
        sc, tp = [], []
        for i in ids:
            s_, t_ = _frame_dets(cands[i], rng.random(len(cands[i])), gts[i], nms)
            sc.append(s_)
            tp.append(t_)
        s_all, t_all = np.concatenate(sc), np.concatenate(tp)
        aps[b] = weighted_voc(s_all, t_all, np.ones(len(s_all)), n_gt)
    return aps


def _ceiling(
    cands: dict[int, np.ndarray], gts: dict[int, np.ndarray], nms: Any, ids: list[int], n_gt: int
) -> tuple[float, int]:
    """The ceiling and the candidates' matches.

    The ceiling: AP50 of the candidates scored by their best IoU with an annotated box. The
    matches: how many annotated boxes some candidate meets at IoU 0.5.
    """
    sc, tp = [], []
    matched = 0
    for i in ids:
        iou = iou_matrix(cands[i], gts[i])
        best = iou.max(axis=1) if iou.shape[1] else np.zeros(len(cands[i]))
        matched += int((iou.max(axis=0) >= 0.5).sum()) if len(cands[i]) else 0
        s_, t_ = _frame_dets(cands[i], best, gts[i], nms)
        sc.append(s_)
        tp.append(t_)
    ceiling = weighted_voc(np.concatenate(sc), np.concatenate(tp), np.ones(sum(map(len, sc))), n_gt)
    return ceiling, matched


def _row_ap(
    per: dict[int, tuple[np.ndarray, np.ndarray]],
    gts: dict[int, np.ndarray],
    ids: list[int],
    n_gt: int,
    counts: np.ndarray,
    gt_n: np.ndarray,
) -> tuple[float, np.ndarray]:
    """A row's AP50 and its AP50 in each bootstrap resample (``counts``) of annotated frames."""
    sc, tp, img = [], [], []
    for k, i in enumerate(ids):
        boxes, scores = per.get(i, (np.zeros((0, 4)), np.zeros(0)))
        order = np.argsort(-scores, kind="stable")
        t_ = np.zeros(len(scores), bool)
        t_[order] = match50(iou_matrix(boxes, gts[i]), order)
        sc.append(scores)
        tp.append(t_)
        img.append(np.full(len(scores), k))
    s_all, t_all, g_all = np.concatenate(sc), np.concatenate(tp), np.concatenate(img)
    ap = weighted_voc(s_all, t_all, np.ones(len(s_all)), n_gt)
    return ap, np.array(
        [weighted_voc(s_all, t_all, c[g_all].astype(np.float64), float(c @ gt_n)) for c in counts]
    )


def table_d_chance(
    cands: dict[int, np.ndarray],
    gts: dict[int, np.ndarray],
    dets: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]],
    nms: Any,
    settings: chance.ChanceSettings,
) -> dict[str, dict[str, Any]]:
    """Method §9 for Table D's AP50: floor, band, ceiling, recall, intervals and verdicts.

    Args:
        cands: the candidate boxes (x1 y1 x2 y2) of each annotated image id.
        gts: the annotated change boxes of each annotated image id (empty: no-change).
        dets: per row (``detector``, ``random``) and image id, the (boxes, scores) it kept.
        nms: ``nms(boxes, scores) -> kept indices`` (the detector's own NMS and cap).
        settings: the random score draws for the floor, the bootstrap resamples of annotated
            frames and their interval level, the seed of both, and the annotated frames holding
            a change box before a row earns a verdict (method §9, evidence before a verdict).

    Returns:
        per row: ``ap50`` (this matcher's; equal to COCOeval's), ``ci_low``/``ci_high``,
        ``vs_random_ci_low``/``_high``, ``verdict``; under ``"chance"``: ``floor``, ``chance_low``,
        ``chance_high``, ``ceiling``, ``candidate_recall``.
    """
    draws, n_boot, ci, seed = settings.draws, settings.n_boot, settings.ci, settings.seed
    ids = sorted(gts)
    n_gt = sum(len(gts[i]) for i in ids)
    rng = np.random.default_rng(chance.draw_seed(seed, "D", n_gt, len(ids)))
    floor, lo, hi = chance.summarise(_random_score_aps(cands, gts, nms, ids, n_gt, draws, rng))
    ceiling, matched = _ceiling(cands, gts, nms, ids, n_gt)
    out: dict[str, dict[str, Any]] = {
        "chance": {
            "floor": floor,
            "chance_low": lo,
            "chance_high": hi,
            "ceiling": ceiling,
            "candidate_recall": matched / n_gt if n_gt else float("nan"),
        }
    }
    counts = resample_counts(len(ids), n_boot, chance.draw_seed(seed, "D-boot", len(ids)))
    gt_n = np.array([len(gts[i]) for i in ids], np.float64)
    boots = {}
    for row, per in dets.items():
        ap, boots[row] = _row_ap(per, gts, ids, n_gt, counts, gt_n)
        bl, bh = interval(boots[row], ci)
        out[row] = {"ap50": ap, "ci_low": bl, "ci_high": bh}
    positive_images = sum(len(gts[i]) > 0 for i in ids)
    for row in dets:
        d = boots[row] - boots.get("random", np.full(len(counts), np.nan))
        dl, dh = interval(d, ci)
        out[row].update({"vs_random_ci_low": dl, "vs_random_ci_high": dh})
        ev = chance.Evidence(positive_images, settings.needed)
        out[row]["positive_images"] = positive_images
        out[row]["verdict"] = chance.verdict(out[row]["ap50"], lo, hi, dl, dh, ev)
    base = [b for b in (*NO_PIXEL, *PIXEL_BASELINES) if b in dets]
    if "detector" in dets and base:  # above only when clear of the best baseline row
        best = max(base, key=lambda b: (out[b]["ap50"], b))
        bl, bh = interval(boots["detector"] - boots[best], ci)
        out["detector"].update(
            {"best_no_pixel": best, "vs_no_pixel_ci_low": bl, "vs_no_pixel_ci_high": bh}
        )
        out["detector"]["verdict"] = chance.versus_no_pixel(out["detector"]["verdict"], bl)
    return out


#: Table D's baselines that read no pixel (method §13.3): the candidates scored by their area, and
#: by how many of the frame's candidates overlap them.
NO_PIXEL = ("size_prior", "cover_count")


def no_pixel_scores(boxes: np.ndarray) -> dict[str, np.ndarray]:
    """Each no-pixel baseline's scores of one frame's candidate boxes (x1 y1 x2 y2)."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    cover = (iou_matrix(b, b) > 0).sum(axis=1).astype(np.float64) if len(b) else np.zeros(0)
    return {"size_prior": area, "cover_count": cover}


def _no_pixel_dets(
    cand: dict[int, np.ndarray], nms: Any
) -> dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """Per no-pixel baseline and image id, the (boxes, scores) the detector's NMS keeps."""
    out: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {b: {} for b in NO_PIXEL}
    for i, boxes in cand.items():
        for name, sc in no_pixel_scores(boxes).items():
            keep = np.asarray(nms(boxes, sc), np.int64)
            out[name][i] = (boxes[keep], sc[keep])
    return out


def _results_of(per: dict[int, tuple[np.ndarray, np.ndarray]]) -> list[dict[str, Any]]:
    """COCO results of per-image (boxes, scores)."""
    return [
        {
            "image_id": int(i),
            "category_id": 1,
            "score": float(s),
            "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])],
        }
        for i in sorted(per)
        for b, s in zip(*per[i], strict=True)
    ]


def _by_image(
    d: pd.DataFrame, ids: dict[tuple[str, str, int], int], on: set[int], score: str
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """(boxes x1 y1 x2 y2, scores) of each image id in ``on``, from rows keyed by frame."""
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    keycols = [c for c in d.columns if c in ("session", "q_session")]
    cols = FRAME_KEY if keycols == ["session"] else QUERY_KEY
    for k, g in d.groupby(cols, sort=True):
        i = ids.get((str(k[0]), str(k[1]), int(k[2])))
        if i in on:
            out[i] = (
                g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64),
                g[score].to_numpy(np.float64),
            )
    return out


#: Table D's rows: the detector and the random baseline (one draw of random scores, same NMS).
D_ROWS = {"detection": "detector", "random": "random scores, same boxes (one draw)"}
#: ... then the baselines that read no pixel (method §13.3), on the same candidates, same NMS.
NO_PIXEL_ROWS = {
    "size_prior": "box area alone (no pixel)",
    "cover_count": "cover count alone (no pixel)",
    "aligned_difference": "aligned difference (pixels, no localizer)",
}


def _coco_results(
    d: pd.DataFrame, ids: dict[tuple[str, str, int], int], on: set[int]
) -> list[dict[str, Any]]:
    """COCO results of the boxes ``d`` on the annotated image ids ``on``."""
    return [
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


def _alarm_columns(
    t: pd.DataFrame, fr: pd.DataFrame, ann: pd.DataFrame, alarm: float, ci: float
) -> None:
    """Method §13.1: the false-alarm rate measured at the nominal rate ``alarm``, added to ``t``.

    Measured on the frames annotated no-change, with its exact interval; and the share of the
    frames annotated with a change that the same rate flags (the detection rate), likewise.
    """
    if "exceedance" not in fr.columns:
        return
    for status, (n, rate, low, high) in ALARM_COLUMNS.items():
        keys = ann[ann["status"] == status][FRAME_KEY].drop_duplicates()
        if not len(keys):
            continue
        f = fr.merge(keys, on=FRAME_KEY)
        k = int((f["exceedance"] <= alarm).sum())
        t["alarm_nominal"], t[n] = alarm, len(f)
        t[rate] = k / len(f) if len(f) else np.nan
        t[low], t[high] = clopper_pearson(k, len(f), ci)


#: Table D's alarm columns by status: frames, the share flagged, its exact interval.
ALARM_COLUMNS = {
    "no-change": ("no_change_frames", "alarm_measured", "alarm_ci_low", "alarm_ci_high"),
    "change": ("changed_frames", "alarm_detected", "detected_ci_low", "detected_ci_high"),
}


@dataclass(frozen=True)
class TableDInputs:
    """What Table D scores: frames, annotations, the detector's boxes, candidates and NMS.

    ``ids`` maps a frame key to its COCO image id; ``cands`` are the candidate boxes (every
    candidate of the annotated frames, keyed by ``q_session, q_camera, q_utime``); ``nms`` the
    detector's NMS (see :func:`table_d_chance`).
    """

    fr: pd.DataFrame
    ann: pd.DataFrame
    dets: pd.DataFrame
    ids: dict[tuple[str, str, int], int]
    cands: pd.DataFrame
    nms: Any


def score_detections(
    out: Path,
    inputs: TableDInputs,
    settings: chance.ChanceSettings,
    boxes: str = "fused",
    alarm: float = 0.01,
) -> pd.DataFrame | None:
    """Table D: the detector's box APs on the annotated query frames, with method §9's floor.

    ``boxes`` names the generator (a column of the table); ``alarm`` is the nominal false-alarm
    rate the alarm columns measure.
    """
    fr, ann, dets, ids, cands, nms = (
        inputs.fr, inputs.ann, inputs.dets, inputs.ids, inputs.cands, inputs.nms
    )  # fmt: skip
    ci, needed = settings.ci, settings.needed
    gt = coco_ground_truth(fr, ann, ids)
    if not gt["images"]:
        return None
    on = {i["id"] for i in gt["images"]}
    write_json(out / "ground_truth.json", gt)
    gts = {i: np.zeros((0, 4)) for i in on}
    for a in gt["annotations"]:
        x, y, w, h = a["bbox"]
        gts[a["image_id"]] = np.vstack([gts[a["image_id"]], [x, y, x + w, y + h]])
    cand = {i: b for i, (b, _) in _by_image(cands, ids, on, "loc").items()}
    cand.update({i: np.zeros((0, 4)) for i in on - set(cand)})
    per_row = {kind: _by_image(dets[dets["kind"] == kind], ids, on, "score") for kind in D_ROWS}
    nopix = {**_no_pixel_dets(cand, nms)}
    if "difference" in cands.columns:  # a run of an older version has none
        nopix.update(difference_dets(_by_image(cands, ids, on, "difference"), nms))
    ch = table_d_chance(
        cand, gts, {"detector": per_row["detection"], "random": per_row["random"], **nopix},
        nms, settings,
    )  # fmt: skip
    rows = []
    for kind, label in {**D_ROWS, **NO_PIXEL_ROWS}.items():
        if kind not in D_ROWS and kind not in nopix:
            continue
        res = (
            _coco_results(dets[dets["kind"] == kind], ids, on)
            if kind in D_ROWS
            else _results_of(nopix[kind])
        )
        voc, coco, coco50 = coco_eval(gt, res)
        c = ch[{"detection": "detector"}.get(kind, kind)]
        rows.append(
            {
                "row": label,
                "ap50_voc_all_point": voc,
                "ci_low": c["ci_low"],
                "ci_high": c["ci_high"],
                **ch["chance"],
                "gap_closed": chance.gap_closed(
                    voc, ch["chance"]["floor"], ch["chance"]["ceiling"]
                ),
                "vs_random_ci_low": c["vs_random_ci_low"],
                "vs_random_ci_high": c["vs_random_ci_high"],
                "verdict": c["verdict"],
                "coco_ap_50_95": coco,
                "coco_ap_50": coco50,
                "annotated_frames": len(gt["images"]),
                "positive_images": c["positive_images"],
                "positive_images_needed": needed,
                "change_boxes": len(gt["annotations"]),
                "detections": len(res),
                "matcher_ap50": c["ap50"],
                "best_no_pixel": c.get("best_no_pixel", ""),
                "vs_no_pixel_ci_low": c.get("vs_no_pixel_ci_low", np.nan),
                "vs_no_pixel_ci_high": c.get("vs_no_pixel_ci_high", np.nan),
            }
        )
    t = pd.DataFrame(rows)
    t.insert(1, "boxes", boxes)
    _alarm_columns(t, fr, ann, alarm, ci)
    write_text(out / "tableD.csv", t.to_csv(index=False, float_format="%.4f"))
    write_text(out / "tableD.md", table_d_markdown(t))
    return t

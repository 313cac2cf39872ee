"""Table D (method §13): ``harness detect``'s change boxes scored on the annotated query frames.

pycocotools' COCOeval does the matching (:mod:`harness.evaluate.box_ap`); COCO AP@[.5:.95] and AP@.5
are its statistics, and the AP at IoU 0.5 with VOC all-point interpolation (the metric of "The
Change You Want to See", WACV 2023) is integrated from its matches.

method §9 for Table D (:func:`table_d_chance`): the floor is the mean AP50 of ``[report]
chance_draws`` draws of random scores on the same candidate boxes (the fused qBBs of every
annotated frame) through the same NMS, the chance band the draws' 5th-95th percentiles; the ceiling
the same candidates scored by their best IoU with an annotated change box, through the same NMS;
the candidates' recall is the share of annotated change boxes that some candidate meets at IoU 0.5.
The draws are matched by :func:`harness.evaluate.box_ap.match50`, COCOeval's greedy matching at
IoU 0.5 (tested equal to pycocotools on the run's own detections), so that 200 draws cost
seconds, not 200 COCOevals.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.boxes import iou_matrix
from harness.evaluate import chance
from harness.evaluate.box_ap import (
    clopper_pearson,
    coco_eval,
    coco_ground_truth,
    coco_results,
    voc_at,
)
from harness.evaluate.table_d_chance import NO_PIXEL, difference_dets, table_d_chance
from harness.records import FRAME_KEY, QUERY_KEY, frame_keys
from harness.runtime.cache import write_json, write_text


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
    ids = [int(i) for i in sorted(per) for _ in per[i][1]]
    boxes = [np.asarray(per[i][0], np.float64).reshape(-1, 4) for i in sorted(per)]
    scores = [float(s) for i in sorted(per) for s in per[i][1]]
    return coco_results(ids, np.concatenate(boxes) if boxes else np.zeros((0, 4)), scores)


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


#: The detector measured apart on the frames whose pairs were registered and on those that were
#: not (compared as they stand, ``[detect] not_comparable = "fallback"``, or kept).
APART_ROWS = {
    True: "detector, registered frames only",
    False: "detector, frames that could not be registered (fallback boxes) only",
}


def _apart(
    inputs: TableDInputs,
    cand: dict[int, np.ndarray],
    gts: dict[int, np.ndarray],
    per_row: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]],
    nms: Any,
    settings: chance.ChanceSettings,
    groups: list[str] | None,
    template: dict[str, Any],
) -> list[dict[str, Any]]:
    """The detector's AP on registered and on unregistered frames apart, each with its chance.

    Only where some annotated frame could not be registered and still has boxes (a fallback):
    boxes drawn on a pair that could not be registered are measured apart (docs/method.md).
    """
    fr, ids = inputs.fr, inputs.ids
    if "comparable" not in fr.columns:
        return []
    ok = {ids[(str(a), str(b), int(c))]: bool(v) for a, b, c, v in
          fr[[*FRAME_KEY, "comparable"]].to_numpy() if (str(a), str(b), int(c)) in ids}  # fmt: skip
    ann_ids = sorted(gts)
    bad = [i for i in ann_ids if not ok.get(i, True)]
    if not bad or not any(len(per_row["detection"].get(i, ((), ()))[1]) for i in bad):
        return []
    out = []
    for flag, label in APART_ROWS.items():
        sub = [i for i in ann_ids if ok.get(i, True) == flag]
        if not sub or not sum(len(gts[i]) for i in sub):
            continue
        g = {i: gts[i] for i in sub}
        gr = None if groups is None else [groups[ann_ids.index(i)] for i in sub]
        rows_ = {
            k: {i: v for i, v in per_row[k].items() if i in g} for k in ("detection", "random")
        }
        ch = table_d_chance(
            {i: cand[i] for i in sub}, g,
            {"detector": rows_["detection"], "random": rows_["random"]}, nms, settings, gr,
        )  # fmt: skip
        c = ch["detector"]
        out.append(
            {
                **{k: np.nan for k in template},
                "row": label,
                "ap50_voc_all_point": c["ap50"],
                "matcher_ap50": c["ap50"],
                "ci_low": c["ci_low"],
                "ci_high": c["ci_high"],
                **{k: v for k, v in ch["chance"].items() if k != "groups"},
                "gap_closed": chance.gap_closed(
                    c["ap50"], ch["chance"]["floor"], ch["chance"]["ceiling"]
                ),
                "vs_random_ci_low": c["vs_random_ci_low"],
                "vs_random_ci_high": c["vs_random_ci_high"],
                "verdict": c["verdict"],
                "annotated_frames": len(sub),
                "positive_images": c["positive_images"],
                "positive_images_needed": settings.needed,
                "change_boxes": sum(len(gts[i]) for i in sub),
                "detections": sum(len(rows_["detection"].get(i, ((), ()))[1]) for i in sub),
                "best_no_pixel": "",
                "bootstrap_group": inputs.grouping,
                "groups": ch["chance"]["groups"],
                "not_comparable_frames": 0 if flag else len(sub),
            }
        )
    return out


def _not_comparable(fr: pd.DataFrame, on: set[int], ids: dict) -> int:
    """How many annotated frames' pairs could not be registered (their changes count as misses)."""
    if "comparable" not in fr.columns:
        return 0
    keys = {k for k, i in ids.items() if i in on}
    f = fr[[(str(a), str(b), int(c)) in keys for a, b, c in fr[FRAME_KEY].to_numpy()]]
    return int((~f["comparable"].astype(bool)).sum())


#: Table D's rows: the detector and the random baseline (one draw of random scores, same NMS).
D_ROWS = {"detection": "detector", "random": "random scores, same boxes (one draw)"}
#: ... then the baselines that read no pixel (method §13.3), on the same candidates, same NMS.
NO_PIXEL_ROWS = {
    "size_prior": "box area alone (no pixel)",
    "cover_count": "cover count alone (no pixel)",
    "plain_difference": "plain difference, registered, its own boxes (pixels, no localizer)",
    "difference_same_boxes": "plain difference on the detector's boxes (pixels, no localizer)",
}


def _coco_results(
    d: pd.DataFrame, ids: dict[tuple[str, str, int], int], on: set[int]
) -> list[dict[str, Any]]:
    """COCO results of the boxes ``d`` on the annotated image ids ``on``."""
    keys = frame_keys(d)
    image = np.array([ids.get(k, -1) for k in keys], np.int64)
    keep = np.isin(image, sorted(on))
    boxes = d[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)[keep]
    return coco_results(image[keep], boxes, d["score"].to_numpy(np.float64)[keep])


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
        flagged = f["exceedance"] <= alarm
        if "comparable" in f.columns:  # a pair that could not be registered raises no alarm
            flagged &= f["comparable"].astype(bool)
        k = int(flagged.sum())
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
    detector's NMS (see :func:`table_d_chance`); ``plain`` the plain difference's own candidates
    and their contrast (same keys); ``groups`` each frame key's bootstrap group and
    ``grouping`` its name (``[detect] bootstrap_group``; None: each frame alone); ``recipe`` the
    plain difference's recipe, named in its row.
    """

    fr: pd.DataFrame
    ann: pd.DataFrame
    dets: pd.DataFrame
    ids: dict[tuple[str, str, int], int]
    cands: pd.DataFrame
    nms: Any
    plain: pd.DataFrame | None = None
    groups: dict[tuple[str, str, int], str] | None = None
    grouping: str = "frame"
    # the plain difference's recipe (``[detect.difference] recipe``), named in its row
    recipe: str = ""


def _difference_rows(
    inputs: TableDInputs, on: set[int]
) -> tuple[dict[str, dict[int, tuple[np.ndarray, np.ndarray]]], dict[str, dict[int, np.ndarray]]]:
    """The rows that read pixels but no localizer, and the candidates of those with their own.

    The plain difference on its own boxes (``inputs.plain``) and on the detector's candidates
    (their ``difference`` column), each through the detector's NMS.
    """
    rows: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
    own: dict[str, dict[int, np.ndarray]] = {}
    if inputs.plain is not None:
        plain = _by_image(inputs.plain, inputs.ids, on, "difference")
        plain.update({i: (np.zeros((0, 4)), np.zeros(0)) for i in on - set(plain)})
        got = difference_dets(plain, inputs.nms, "plain_difference")
        if got:
            rows.update(got)
            own["plain_difference"] = {i: b for i, (b, _) in plain.items()}
    if "difference" in inputs.cands.columns:
        same = _by_image(inputs.cands, inputs.ids, on, "difference")
        rows.update(difference_dets(same, inputs.nms, "difference_same_boxes"))
    return rows, own


#: The loose IoU Table D gives beside 0.5 (docs/method.md, *Loose labels*).
LOOSE_IOU = 0.3


def _table_row(
    label: str,
    aps: tuple[float, float, float, float, float],
    c: dict[str, Any],
    ch: dict[str, Any],
    gt: dict[str, Any],
    detections: int,
    inputs: TableDInputs,
    needed: int,
) -> dict[str, Any]:
    """One row of Table D: COCOeval's APs (VOC AP50, AP@[.5:.95], AP@.5) and method §9's."""
    voc, coco, coco50, voc30, offset = aps
    own = c.get("chance", ch["chance"])  # a row on candidates of its own has its own chance
    on = {i["id"] for i in gt["images"]}
    return {
        "row": label,
        "ap50_voc_all_point": voc,
        "ap30_voc_all_point": voc30,
        "centre_offset_px": offset,
        "ci_low": c["ci_low"],
        "ci_high": c["ci_high"],
        **{k: v for k, v in own.items() if k != "groups"},
        "gap_closed": chance.gap_closed(voc, own["floor"], own["ceiling"]),
        "vs_random_ci_low": c["vs_random_ci_low"],
        "vs_random_ci_high": c["vs_random_ci_high"],
        "verdict": c["verdict"],
        "coco_ap_50_95": coco,
        "coco_ap_50": coco50,
        "annotated_frames": len(gt["images"]),
        "positive_images": c["positive_images"],
        "positive_images_needed": needed,
        "change_boxes": len(gt["annotations"]),
        "detections": detections,
        "matcher_ap50": c["ap50"],
        "best_no_pixel": c.get("best_no_pixel", ""),
        "vs_no_pixel_ci_low": c.get("vs_no_pixel_ci_low", np.nan),
        "vs_no_pixel_ci_high": c.get("vs_no_pixel_ci_high", np.nan),
        "vs_plain": c.get("vs_plain", np.nan),
        "vs_plain_ci_low": c.get("vs_plain_ci_low", np.nan),
        "vs_plain_ci_high": c.get("vs_plain_ci_high", np.nan),
        "bootstrap_group": inputs.grouping,
        "groups": ch["chance"]["groups"],
        "not_comparable_frames": _not_comparable(inputs.fr, on, inputs.ids),
    }


def score_detections(
    out: Path,
    inputs: TableDInputs,
    settings: chance.ChanceSettings,
    boxes: str = "fused",
    alarm: float = 0.01,
) -> pd.DataFrame | None:
    """Table D: the detector's box APs on the annotated query frames, with method §9's floor.

    Writes ``ground_truth.json`` and ``tableD.csv``; the caller renders the table
    (:func:`harness.reports.table_d.table_d_markdown`).

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
    nopix, own = _difference_rows(inputs, on)
    nopix = {**_no_pixel_dets(cand, nms), **nopix}
    key_of = {v: k for k, v in ids.items()}
    groups = (
        None
        if inputs.groups is None
        else [inputs.groups.get(key_of[i], str(i)) for i in sorted(gts)]
    )
    ch = table_d_chance(
        cand, gts, {"detector": per_row["detection"], "random": per_row["random"], **nopix},
        nms, settings, groups, own,
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
        voc30, offsets = voc_at(gt, res, LOOSE_IOU)
        offset = float(np.median(offsets)) if len(offsets) else np.nan
        c = ch[{"detection": "detector"}.get(kind, kind)]
        aps = (voc, coco, coco50, voc30, offset)
        if kind == "plain_difference" and inputs.recipe:
            label = f"{label.removesuffix(')')}; {inputs.recipe} recipe)"
        rows.append(_table_row(label, aps, c, ch, gt, len(res), inputs, needed))
    rows += _apart(inputs, cand, gts, per_row, nms, settings, groups, rows[0])
    t = pd.DataFrame(rows)
    t.insert(1, "boxes", boxes)
    _alarm_columns(t, fr, ann, alarm, ci)
    write_text(out / "tableD.csv", t.to_csv(index=False, float_format="%.4f"))
    return t

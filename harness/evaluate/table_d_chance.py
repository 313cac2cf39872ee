"""Table D's floors, chance bands, ceilings, grouped intervals and verdicts (method §9, §13.5).

The floor is the mean AP50 of ``[report] chance_draws`` draws of random scores on the same
candidate boxes through the same NMS, the chance band the draws' 5th-95th percentiles; the ceiling
the same candidates scored by their best IoU with an annotated change box; the candidates' recall
the share of annotated change boxes some candidate meets at IoU 0.5. Intervals and paired
differences resample annotated frames, or whole groups of them (``[detect] bootstrap_group``).
The draws are matched by :func:`harness.evaluate.box_ap.match50`, COCOeval's greedy matching at
IoU 0.5 (tested equal to pycocotools on the run's own detections), so that 200 draws cost seconds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.boxes import iou_matrix
from harness.evaluate import chance
from harness.evaluate.box_ap import match50, match50_rows, weighted_voc
from harness.evaluate.metrics import interval, resample_counts

#: Table D's rows that read the pair's pixels but no localizer: the plain difference with its own
#: boxes (Selective Search), and the detector's candidates scored by the same difference. The
#: detector is above only when it clears these rows too.
PIXEL_BASELINES = ("plain_difference", "difference_same_boxes")


def difference_dets(
    by_image: dict[int, tuple[np.ndarray, np.ndarray]], nms: Any, row: str
) -> dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """A difference row: per image id, the (boxes, scores) the detector's NMS keeps.

    Boxes without a difference (a pair that is not comparable) never enter; none where no box
    carries one.
    """
    if not any(np.isfinite(sc).any() for _, sc in by_image.values()):
        return {}
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for i, (boxes, sc) in by_image.items():
        keep = np.asarray(nms(boxes, sc), np.int64)
        out[i] = (boxes[keep], sc[keep])
    return {row: out}


#: Table D's baselines that read no pixel (method §13.3): the candidates scored by their area, and
#: by how many of the frame's candidates overlap them.
NO_PIXEL = ("size_prior", "cover_count")


def _frame_dets(
    boxes: np.ndarray,
    scores: np.ndarray,
    gt: np.ndarray,
    nms: Any,
    iou: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(scores, true-positive flags) of one frame's detections: ``nms`` keeps, COCO matches.

    ``iou``: ``iou_matrix(boxes, gt)`` where it was made before (its rows are the kept boxes').
    """
    keep = np.asarray(nms(boxes, scores), np.int64)
    if not len(keep):
        return np.zeros(0), np.zeros(0, bool)
    sc = scores[keep]
    order = np.argsort(-sc, kind="stable")
    tp = np.zeros(len(keep), bool)
    tp[order] = match50(iou_matrix(boxes[keep], gt) if iou is None else iou[keep], order)
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
    """AP50 of ``draws`` random scorings of the candidates, through the detector's NMS.

    Draw by draw, frame by frame in ``ids`` order, each frame's scores ``rng.random(n)``. Where
    ``nms`` keeps boxes for many score rows at once (:meth:`harness.boxes.FrameNMS.many`),
    each frame's draws go through it together: the same numbers, boxes and APs.
    """
    if not hasattr(nms, "many"):
        return _random_score_aps_one(cands, gts, nms, ids, n_gt, draws, rng)
    sizes = [len(cands[i]) for i in ids]
    scores = rng.random(draws * sum(sizes)).reshape(draws, -1)  # the numbers drawn one by one
    at = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    sc, tp, ok = [], [], []
    for k, i in enumerate(ids):
        s_ = scores[:, at[k] : at[k + 1]]
        kept = nms.many(cands[i], s_)
        sc.append(np.take_along_axis(s_, np.maximum(kept, 0), axis=1) if s_.shape[1] else
                  np.zeros(kept.shape))  # fmt: skip
        tp.append(match50_rows(iou_matrix(cands[i], gts[i]), kept))
        ok.append(kept >= 0)
    s_all, t_all, v_all = (np.concatenate(x, axis=1) for x in (sc, tp, ok))
    aps = np.empty(draws)
    for b in range(draws):
        s, t = s_all[b][v_all[b]], t_all[b][v_all[b]]
        aps[b] = weighted_voc(s, t, np.ones(len(s)), n_gt)
    return aps


def _random_score_aps_one(
    cands: dict[int, np.ndarray],
    gts: dict[int, np.ndarray],
    nms: Any,
    ids: list[int],
    n_gt: int,
    draws: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """:func:`_random_score_aps` through an ``nms`` of one score set at a time."""
    aps = np.empty(draws)
    ious = {i: iou_matrix(cands[i], gts[i]) for i in ids}  # each frame's once, for every draw
    for b in range(draws):
        sc, tp = [], []
        for i in ids:
            s_, t_ = _frame_dets(cands[i], rng.random(len(cands[i])), gts[i], nms, ious[i])
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


def _chance_of(
    cands: dict[int, np.ndarray],
    gts: dict[int, np.ndarray],
    nms: Any,
    settings: chance.ChanceSettings,
    salt: str = "D",
) -> dict[str, Any]:
    """Method §9's floor, chance band, ceiling and recall of one set of candidate boxes."""
    ids = sorted(gts)
    n_gt = sum(len(gts[i]) for i in ids)
    rng = np.random.default_rng(chance.draw_seed(settings.seed, salt, n_gt, len(ids)))
    aps = _random_score_aps(cands, gts, nms, ids, n_gt, settings.draws, rng)
    floor, lo, hi = chance.summarise(aps)
    ceiling, matched = _ceiling(cands, gts, nms, ids, n_gt)
    return {
        "floor": floor,
        "chance_low": lo,
        "chance_high": hi,
        "ceiling": ceiling,
        "candidate_recall": matched / n_gt if n_gt else float("nan"),
    }


def _random_dets(
    cands: dict[int, np.ndarray], nms: Any, seed: int
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """One draw of random scores on ``cands``, through ``nms`` (a row's own random baseline)."""
    rng = np.random.default_rng(chance.draw_seed(seed, "D-own-random", len(cands)))
    out = {}
    for i in sorted(cands):
        sc = rng.random(len(cands[i]))
        keep = np.asarray(nms(cands[i], sc), np.int64)
        out[i] = (cands[i][keep], sc[keep])
    return out


def group_counts(
    groups: list[str] | None, n: int, n_boot: int, seed: int
) -> tuple[np.ndarray, int]:
    """(n_boot, n) multiplicities of each annotated frame when whole groups are resampled.

    ``groups``: each frame's group (None: each frame its own). Returns the counts and the number
    of groups.
    """
    if groups is None:
        return resample_counts(n, n_boot, chance.draw_seed(seed, "D-boot", n)), n
    names = sorted(set(groups))
    idx = np.array([names.index(g) for g in groups], np.int64)
    by_group = resample_counts(len(names), n_boot, chance.draw_seed(seed, "D-boot", n, len(names)))
    return by_group[:, idx] if n else by_group[:, :0], len(names)


def table_d_chance(
    cands: dict[int, np.ndarray],
    gts: dict[int, np.ndarray],
    dets: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]],
    nms: Any,
    settings: chance.ChanceSettings,
    groups: list[str] | None = None,
    own: dict[str, dict[int, np.ndarray]] | None = None,
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
        groups: each annotated image id's group, in sorted id order: a resample draws whole
            groups (None: each frame alone).
        own: rows that draw their boxes from candidates of their own (the plain difference):
            their floor, band and ceiling are of those candidates, and their verdict is against a
            random draw on them.

    Returns:
        per row: ``ap50`` (this matcher's; equal to COCOeval's), ``ci_low``/``ci_high``,
        ``vs_random_ci_low``/``_high``, ``verdict``, and for own-candidate rows their ``chance``;
        under ``"chance"``: ``floor``, ``chance_low``, ``chance_high``, ``ceiling``,
        ``candidate_recall``, ``groups``; the detector's paired differences from the best
        baseline and from the plain difference (``vs_plain_*``).
    """
    n_boot, ci, seed = settings.n_boot, settings.ci, settings.seed
    own = own or {}
    ids = sorted(gts)
    n_gt = sum(len(gts[i]) for i in ids)
    out: dict[str, dict[str, Any]] = {"chance": _chance_of(cands, gts, nms, settings)}
    counts, n_groups = group_counts(groups, len(ids), n_boot, seed)
    out["chance"]["groups"] = n_groups
    gt_n = np.array([len(gts[i]) for i in ids], np.float64)
    rows = {**dets}
    for row, oc in own.items():  # each own-candidate row beside its own random draw
        rows[f"{row}:random"] = _random_dets(oc, nms, seed)
    boots = {}
    for row, per in rows.items():
        ap, boots[row] = _row_ap(per, gts, ids, n_gt, counts, gt_n)
        bl, bh = interval(boots[row], ci)
        out[row] = {"ap50": ap, "ci_low": bl, "ci_high": bh}
    positive_images = sum(len(gts[i]) > 0 for i in ids)
    for row in dets:
        ch = out["chance"]
        rnd = "random"
        if row in own:
            ch = out[row]["chance"] = _chance_of(own[row], gts, nms, settings, f"D-{row}")
            rnd = f"{row}:random"
        d = boots[row] - boots.get(rnd, np.full(len(counts), np.nan))
        dl, dh = interval(d, ci)
        out[row].update({"vs_random_ci_low": dl, "vs_random_ci_high": dh})
        ev = chance.Evidence(positive_images, settings.needed)
        out[row]["positive_images"] = positive_images
        out[row]["verdict"] = chance.verdict(
            out[row]["ap50"], ch["chance_low"], ch["chance_high"], dl, dh, ev
        )
    base = [b for b in (*NO_PIXEL, *PIXEL_BASELINES) if b in dets]
    if "detector" in dets and base:  # above only when clear of the best baseline row
        best = max(base, key=lambda b: (out[b]["ap50"], b))
        bl, bh = interval(boots["detector"] - boots[best], ci)
        out["detector"].update(
            {"best_no_pixel": best, "vs_no_pixel_ci_low": bl, "vs_no_pixel_ci_high": bh}
        )
        out["detector"]["verdict"] = chance.versus_no_pixel(out["detector"]["verdict"], bl)
    if "detector" in dets and "plain_difference" in dets:  # what localization adds
        dl, dh = interval(boots["detector"] - boots["plain_difference"], ci)
        vs = out["detector"]["ap50"] - out["plain_difference"]["ap50"]
        out["detector"].update({"vs_plain": vs, "vs_plain_ci_low": dl, "vs_plain_ci_high": dh})
    return out

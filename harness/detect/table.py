"""Table D (SPEC 13.1, section 9 for its floor and ceiling): its markdown, its HTML, its warnings.

:func:`harness.detect.evaluate.score_detections` computes the table (``tableD.csv``); the markdown
file and the page (:mod:`harness.detect.page`) show it from here.
"""

from __future__ import annotations

import pandas as pd

from harness.evaluate.chance import MARK_LEGEND, VERDICT_WORDS
from harness.reports.html.cells import esc


def table_d_markdown(t: pd.DataFrame) -> str:
    """Table D as markdown, with what each column measures and SPEC 9's floor, band, ceiling."""
    c = t.iloc[0]
    lines = [
        "# Table D: change boxes on the annotated query frames"
        + (f" (boxes: {c.boxes})" if "boxes" in t.columns else ""),
        "",
        "Box AP of the detector's change boxes (SPEC 13) against the annotated change boxes, by "
        "pycocotools' COCOeval: AP at IoU 0.5 with VOC all-point interpolation (the metric of "
        "'The Change You Want to See', WACV 2023) with its 95% bootstrap interval over annotated "
        "frames, COCO AP@[.5:.95] and COCO AP@.5 (101-point). Frames annotated no-change "
        "contribute false positives only.",
        "",
        "| | AP50 (VOC all-point) [95% CI] | verdict | COCO AP@[.5:.95] | COCO AP@.5 | frames | "
        "change boxes | detections |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in t.itertuples():
        lines.append(
            f"| {r.row} | {r.ap50_voc_all_point:.3f} [{r.ci_low:.3f}, {r.ci_high:.3f}] | "
            f"{VERDICT_WORDS[r.verdict]} | {r.coco_ap_50_95:.3f} | {r.coco_ap_50:.3f} | "
            f"{r.annotated_frames} | {r.change_boxes} | {r.detections} |"
        )
    lines += [
        "",
        "| AP50 of the candidate boxes | value |",
        "|---|---:|",
        f"| floor (mean AP50 of random scores on the same candidates, same NMS) | {c.floor:.3f} |",
        f"| chance band (5th-95th percentile of those draws) | {c.chance_low:.3f}-"
        f"{c.chance_high:.3f} |",
        f"| ceiling (candidates scored by their best IoU with a change box, same NMS) | "
        f"{c.ceiling:.3f} |",
        f"| candidates' recall at IoU 0.5 (change boxes some candidate meets) | "
        f"{c.candidate_recall:.3f} |",
        f"| share of the reachable gap the detector closes, (AP - floor) / (ceiling - floor) | "
        f"{_pct(c.gap_closed)} |",
        *(
            [
                f"| nominal false-alarm rate (frames whose calibrated score is at most it) | "
                f"{c.alarm_nominal:g} |",
                f"| false-alarm rate measured on the {int(c.no_change_frames)} frames annotated "
                f"no-change [95% exact interval] | {c.alarm_measured:.3f} "
                f"[{c.alarm_ci_low:.3f}, {c.alarm_ci_high:.3f}] |",
            ]
            if "alarm_measured" in t.columns and int(c.no_change_frames)
            else []
        ),
        "",
        f"Verdict (SPEC 9): {MARK_LEGEND}",
    ]
    lines += ["", *table_d_warnings(t)]
    return "\n".join(lines) + "\n"


def _pct(v: float) -> str:
    return "NaN" if v != v else f"{100 * v:.0f}%"


def table_d_html(table_d: pd.DataFrame | None) -> str:
    """Table D with its floor, chance band, ceiling, candidates' recall and false-alarm rates."""
    if table_d is None:
        return ""
    rows = "".join(
        f"<tr><td>{esc(x.row)}</td><td data-verdict='{esc(x.verdict)}'>"
        f"{x.ap50_voc_all_point:.3f} [{x.ci_low:.3f}, {x.ci_high:.3f}]</td>"
        f"<td>{esc(VERDICT_WORDS[x.verdict])}</td>"
        f"<td>{x.coco_ap_50_95:.3f}</td><td>{x.coco_ap_50:.3f}</td>"
        f"<td>{x.annotated_frames}</td><td>{x.change_boxes}</td><td>{x.detections}</td></tr>"
        for x in table_d.itertuples()
    )
    c = table_d.iloc[0]
    gen = f" (boxes: {esc(c.boxes)})" if "boxes" in table_d.columns else ""  # the generator
    td = (
        f'<h2 id="tableD">Table D: change boxes on the annotated frames{gen}</h2>'
        "<p class='note'>pycocotools' COCOeval; AP50 with VOC all-point interpolation and "
        "its 95% bootstrap interval over annotated frames, COCO AP@[.5:.95]; frames annotated "
        "no-change give false positives only. Verdict by SPEC 9: above chance only above the "
        "chance band and clear of the random row (paired).</p>"
        '<table data-table="D"><tr><th></th><th>AP50 (VOC all-point)</th><th>verdict</th>'
        "<th>COCO AP@[.5:.95]</th><th>COCO AP@.5</th><th>frames</th><th>change boxes</th>"
        f"<th>detections</th></tr>{rows}</table>"
        f"<p class='note' data-chance='D'>AP50 of these candidate boxes: floor {c.floor:.3f} "
        f"(mean of random scores, same NMS), chance band {c.chance_low:.3f}-"
        f"{c.chance_high:.3f}, ceiling {c.ceiling:.3f} (candidates scored by their best IoU), "
        f"candidates' recall at IoU 0.5 {c.candidate_recall:.3f}.</p>"
    )
    if "alarm_measured" in table_d.columns and int(c.no_change_frames):
        td += (
            f"<p class='note' data-alarm='{c.alarm_nominal:g}'>Calibrated scores: at a "
            f"nominal false-alarm rate of {c.alarm_nominal:g}, "
            f"{c.alarm_measured:.3f} [{c.alarm_ci_low:.3f}, {c.alarm_ci_high:.3f}] (95% exact "
            f"interval) of the {int(c.no_change_frames)} frames annotated no-change are "
            "flagged.</p>"
        )
    return td + "".join(f'<p class="warn">{esc(w)}</p>' for w in table_d_warnings(table_d))


def table_d_warnings(t: pd.DataFrame) -> list[str]:
    """What Table D must say in words, from SPEC 9's verdict and the candidates' ceiling."""
    out = []
    det = t.iloc[0]
    if det["verdict"] != "above":
        out.append(
            f"WARNING: the detector's AP50 ({det['ap50_voc_all_point']:.3f}): "
            f"{VERDICT_WORDS[str(det['verdict'])]} (floor {det['floor']:.3f}, chance band "
            f"{det['chance_low']:.3f}-{det['chance_high']:.3f}, paired difference from the "
            f"random row [{det['vs_random_ci_low']:+.3f}, {det['vs_random_ci_high']:+.3f}]): its "
            "boxes locate the annotated changes no better than random scores on the same "
            "candidates. The frame scores (image AP in Table P of harness reproduce) and the LoC "
            "maps may still rank changed frames and regions first."
        )
    if det["candidate_recall"] == det["candidate_recall"] and det["candidate_recall"] < 0.5:
        out.append(
            f"NOTE: only {det['candidate_recall']:.0%} of the annotated change boxes are met at "
            "IoU 0.5 by any candidate box (fused qBBs are intersections of proposals, usually "
            f"smaller than a change object): no score could lift AP50 above the ceiling "
            f"{det['ceiling']:.3f}. The loss is in the boxes, not the localizer."
        )
    if int(det["annotated_frames"]) < 30:
        out.append(
            f"NOTE: {int(det['annotated_frames'])} annotated query frames: too few for these APs "
            "to be more than an indication."
        )
    return out

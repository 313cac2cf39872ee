"""Table D (method §13.1, section 9 for its floor and ceiling), built once for every format.

:func:`harness.evaluate.table_d.score_detections` computes the table (``tableD.csv``, a row per
detector and baseline with the candidates' floor, band, ceiling, recall and false-alarm rates);
:func:`table_d` turns it into a :class:`TableD` (each row's cells as text, the candidates'
figures, the false-alarm rates, the warnings) that the markdown file and the page
(:mod:`harness.reports.detect_page`) render.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from harness.evaluate.chance import MARK_LEGEND, VERDICT_WORDS, few_text, few_warning
from harness.reports.html import esc

#: Table D's columns after the row's name (the page's headings drop the `` [95% CI]``).
COLUMNS = (
    "AP50 (VOC all-point) [95% CI]",
    "verdict",
    "AP30 (VOC all-point)",
    "COCO AP@[.5:.95]",
    "COCO AP@.5",
    "frames",
    "change boxes",
    "detections",
)


@dataclass(frozen=True)
class DRow:
    """One row of Table D: its name, method §9's verdict and a text cell per :data:`COLUMNS`."""

    name: str
    verdict: str
    cells: tuple[str, ...]


@dataclass(frozen=True)
class Alarm:
    """The calibrated scores' false-alarm rate: nominal, and measured on no-change frames."""

    nominal: float
    measured: float
    low: float
    high: float
    frames: int
    # the share of the frames annotated with a change that the same rate flags, its interval
    detected: float = float("nan")
    detected_low: float = float("nan")
    detected_high: float = float("nan")
    changed: int = 0


@dataclass(frozen=True)
class TableD:
    """Table D ready for any format: rows, the candidates' method §9 figures, alarms, warnings."""

    generator: str
    rows: tuple[DRow, ...]
    floor: float
    chance_low: float
    chance_high: float
    ceiling: float
    candidate_recall: float
    gap_closed: float
    alarm: Alarm | None
    warnings: tuple[str, ...]


def _count(c: Any, col: str) -> int:
    """A count column of Table D's first row (0 where absent or NaN)."""
    v = getattr(c, col, 0)
    return int(v) if v == v else 0


def _alarm(t: pd.DataFrame) -> Alarm | None:
    """The alarm columns as an :class:`Alarm` (None where no frame is annotated either way)."""
    c = t.iloc[0]
    quiet, changed = _count(c, "no_change_frames"), _count(c, "changed_frames")
    if not quiet and not changed:
        return None
    nan = float("nan")
    return Alarm(
        float(c.alarm_nominal),
        *((float(c.alarm_measured), float(c.alarm_ci_low), float(c.alarm_ci_high)) if quiet
          else (nan, nan, nan)),
        quiet,
        *((float(c.alarm_detected), float(c.detected_ci_low), float(c.detected_ci_high)) if changed
          else (nan, nan, nan)),
        changed,
    )  # fmt: skip


def table_d(t: pd.DataFrame) -> TableD:
    """Table D (``score_detections``'s frame, or ``tableD.csv`` read back) for every format."""
    rows = tuple(
        DRow(
            str(r.row),
            str(r.verdict),
            (
                f"{r.ap50_voc_all_point:.3f} [{r.ci_low:.3f}, {r.ci_high:.3f}]",
                few_text(int(getattr(r, "positive_images", 0)))
                if r.verdict == "few"
                else VERDICT_WORDS[r.verdict],
                f"{getattr(r, 'ap30_voc_all_point', float('nan')):.3f}",
                f"{r.coco_ap_50_95:.3f}",
                f"{r.coco_ap_50:.3f}",
                f"{r.annotated_frames}",
                f"{r.change_boxes}",
                f"{r.detections}",
            ),
        )
        for r in t.itertuples()
    )
    c = t.iloc[0]
    alarm = _alarm(t) if "alarm_nominal" in t.columns else None
    return TableD(
        str(c.boxes) if "boxes" in t.columns else "",
        rows,
        float(c.floor),
        float(c.chance_low),
        float(c.chance_high),
        float(c.ceiling),
        float(c.candidate_recall),
        float(c.gap_closed),
        alarm,
        tuple(table_d_warnings(t)),
    )


def table_d_markdown(t: pd.DataFrame) -> str:
    """Table D as markdown, with what each column measures and method §9's floor, band, ceiling."""
    v = table_d(t)
    lines = [
        "# Table D: change boxes on the annotated query frames"
        + (f" (boxes: {v.generator})" if v.generator else ""),
        "",
        "Box AP of the detector's change boxes (method §13) against the annotated change boxes, by "
        "pycocotools' COCOeval: AP at IoU 0.5 with VOC all-point interpolation (the metric of "
        "'The Change You Want to See', WACV 2023) with its 95% bootstrap interval over annotated "
        "frames, COCO AP@[.5:.95] and COCO AP@.5 (101-point). Frames annotated no-change "
        "contribute false positives only.",
        "",
        "| | " + " | ".join(COLUMNS) + " |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|",
        *(f"| {r.name} | " + " | ".join(r.cells) + " |" for r in v.rows),
        "",
        "| AP50 of the candidate boxes | value |",
        "|---|---:|",
        f"| floor (mean AP50 of random scores on the same candidates, same NMS) | {v.floor:.3f} |",
        f"| chance band (5th-95th percentile of those draws) | {v.chance_low:.3f}-"
        f"{v.chance_high:.3f} |",
        f"| ceiling (candidates scored by their best IoU with a change box, same NMS) | "
        f"{v.ceiling:.3f} |",
        f"| candidates' recall at IoU 0.5 (change boxes some candidate meets) | "
        f"{v.candidate_recall:.3f} |",
        f"| share of the reachable gap the detector closes, (AP - floor) / (ceiling - floor) | "
        f"{_pct(v.gap_closed)} |",
    ]
    if v.alarm:
        a = v.alarm
        lines += [
            f"| nominal false-alarm rate (frames whose calibrated score is at most it) | "
            f"{a.nominal:g} |",
        ]
        if a.frames:
            lines.append(
                f"| false-alarm rate measured on the {a.frames} frames annotated no-change "
                f"[95% exact interval] | {a.measured:.3f} [{a.low:.3f}, {a.high:.3f}] |"
            )
        if a.changed:
            lines.append(
                f"| changed frames flagged at that rate, of the {a.changed} annotated with a "
                f"change [95% exact interval] (chance: a score drawn like the null's is flagged at "
                f"the nominal rate) | {a.detected:.3f} [{a.detected_low:.3f}, "
                f"{a.detected_high:.3f}] |"
            )
    lines += ["", f"Verdict (method §9): {MARK_LEGEND} {NO_PIXEL_RULE}", "", *v.warnings]
    return "\n".join(lines) + "\n"


#: method §13.3's addition to the verdict legend of Table D.
NO_PIXEL_RULE = (
    "The detector is above chance only when its paired bootstrap difference from the best "
    "no-pixel row (box area, cover count: the same candidates ranked without reading a pixel) "
    "is also clear above 0; otherwise it says so (method §13.3)."
)


#: AP at IoU 0.3 this many times AP50 or more: the boxes or the labels are loose.
LOOSE_RATIO = 1.5


def _pct(v: float) -> str:
    return "NaN" if v != v else f"{100 * v:.0f}%"


def table_d_html(t: pd.DataFrame | None) -> str:
    """Table D with its floor, chance band, ceiling, candidates' recall and false-alarm rates."""
    if t is None:
        return ""
    v = table_d(t)
    rows = "".join(
        f"<tr><td>{esc(r.name)}</td><td data-verdict='{esc(r.verdict)}'>{r.cells[0]}</td>"
        + "".join(f"<td>{esc(c)}</td>" for c in r.cells[1:])
        + "</tr>"
        for r in v.rows
    )
    head = "".join(f"<th>{h.removesuffix(' [95% CI]')}</th>" for h in COLUMNS)
    gen = f" (boxes: {esc(v.generator)})" if v.generator else ""
    td = (
        f'<h2 id="tableD">Table D: change boxes on the annotated frames{gen}</h2>'
        "<p class='note'>pycocotools' COCOeval; AP50 with VOC all-point interpolation and "
        "its 95% bootstrap interval over annotated frames, COCO AP@[.5:.95]; frames annotated "
        "no-change give false positives only. Verdict by method §9: above chance only above the "
        "chance band and clear of the random row (paired); the detector also clear of the best "
        "no-pixel row (method §13.3).</p>"
        f'<table data-table="D"><tr><th></th>{head}</tr>{rows}</table>'
        f"<p class='note' data-chance='D'>AP50 of these candidate boxes: floor {v.floor:.3f} "
        f"(mean of random scores, same NMS), chance band {v.chance_low:.3f}-"
        f"{v.chance_high:.3f}, ceiling {v.ceiling:.3f} (candidates scored by their best IoU), "
        f"candidates' recall at IoU 0.5 {v.candidate_recall:.3f}.</p>"
    )
    if v.alarm:
        a = v.alarm
        td += (
            f"<p class='note' data-alarm='{a.nominal:g}'>Calibrated scores: at a "
            f"nominal false-alarm rate of {a.nominal:g}, "
            + " and ".join(
                part
                for part, here in (
                    (
                        f"{a.measured:.3f} [{a.low:.3f}, {a.high:.3f}] (95% exact interval) of "
                        f"the {a.frames} frames annotated no-change",
                        a.frames,
                    ),
                    (
                        f"{a.detected:.3f} [{a.detected_low:.3f}, {a.detected_high:.3f}] of the "
                        f"{a.changed} frames annotated with a change (chance: the nominal rate)",
                        a.changed,
                    ),
                )
                if here
            )
            + " are flagged.</p>"
        )
    return td + "".join(f'<p class="warn">{esc(w)}</p>' for w in v.warnings)


def table_d_warnings(t: pd.DataFrame) -> list[str]:
    """What Table D must say in words, from method §9's verdict and the candidates' ceiling."""
    out = []
    det = t.iloc[0]
    if det["verdict"] == "few":
        out.append(
            few_warning(int((t["verdict"] == "few").sum()), int(det["positive_images_needed"]))
        )
    elif det["verdict"] not in ("above", "baseline"):
        out.append(
            f"WARNING: the detector's AP50 ({det['ap50_voc_all_point']:.3f}): "
            f"{VERDICT_WORDS[str(det['verdict'])]} (floor {det['floor']:.3f}, chance band "
            f"{det['chance_low']:.3f}-{det['chance_high']:.3f}, paired difference from the "
            f"random row [{det['vs_random_ci_low']:+.3f}, {det['vs_random_ci_high']:+.3f}]): its "
            "boxes locate the annotated changes no better than random scores on the same "
            "candidates. The frame scores (image AP in Table P of harness reproduce) and the LoC "
            "maps may still rank changed frames and regions first."
        )
    out += _no_pixel_warnings(t)
    out += table_d_findings(t)
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


def table_d_findings(t: pd.DataFrame) -> list[str]:
    """What Table D rests on and what localization adds, in words (docs/method.md).

    The bootstrap's groups, the annotated frames whose pairs could not be registered, the plain
    difference row's own chance band, and the detector against the plain difference by the
    paired test: better, worse, or not told apart.
    """
    det, out = t.iloc[0], []
    if "groups" in t.columns:
        how = {"map_image": "the map image they were compared with", "frame": "frame"}
        out.append(
            f"NOTE: intervals and paired tests resample {int(det['groups'])} groups of the "
            f"{int(det['annotated_frames'])} annotated frames (grouped by "
            f"{how.get(str(det['bootstrap_group']), str(det['bootstrap_group']))}): pairs that "
            "share a view are not independent samples."
        )
    if "not_comparable_frames" in t.columns and int(det["not_comparable_frames"]):
        apart = t["row"].str.startswith("detector, frames that could not")
        what = (
            "the boxes drawn there compare the pair without a registration (by the colours' "
            "novelty, or a fallback warp) and are measured apart in the rows below the baselines"
            if apart.any()
            else "no change box is drawn there, and their annotated changes count as misses in "
            "every row"
        )
        out.append(
            f"NOTE: {int(det['not_comparable_frames'])} of {int(det['annotated_frames'])} "
            f"annotated frames could not be registered with their map frame (not comparable): "
            f"{what}."
        )
    plain = t[t["row"].str.startswith("plain difference, registered")]
    if len(plain):
        p = plain.iloc[0]
        out.append(
            f"NOTE: the plain difference ranks boxes of its own (Selective Search on the query "
            f"frame): floor {p['floor']:.3f}, chance band {p['chance_low']:.3f}-"
            f"{p['chance_high']:.3f}, ceiling {p['ceiling']:.3f}, recall at IoU 0.5 "
            f"{p['candidate_recall']:.3f}."
        )
    out += _loose_labels(det)
    if "vs_plain" in t.columns and det["vs_plain"] == det["vs_plain"]:
        lo, hi = float(det["vs_plain_ci_low"]), float(det["vs_plain_ci_high"])
        if lo > 0:
            word = "better than the plain difference alone: localization adds to it here"
        elif hi < 0:
            word = "worse than the plain difference alone: localization costs here"
        else:
            word = (
                "not told apart from the plain difference alone: localization adds nothing "
                "measurable here"
            )
        out.append(
            f"WHAT LOCALIZATION ADDS: the detector's AP50 is {word} (paired difference "
            f"{float(det['vs_plain']):+.3f} [{lo:+.3f}, {hi:+.3f}])."
        )
    return out


def _loose_labels(det: pd.Series) -> list[str]:
    """A NOTE where the detector's AP at IoU 0.3 is :data:`LOOSE_RATIO` times its AP50 or more."""
    ap30, ap50 = float(det.get("ap30_voc_all_point", np.nan)), float(det["ap50_voc_all_point"])
    if ap30 != ap30 or ap30 < LOOSE_RATIO * ap50 or ap30 <= 0:
        return []
    offset = float(det.get("centre_offset_px", np.nan))
    return [
        f"NOTE: loose boxes or loose labels: the detector's AP at IoU 0.3 ({ap30:.3f}) is "
        + (f"{ap30 / ap50:.1f} times" if ap50 > 0 else "far above")
        + f" its AP50 ({ap50:.3f})."
        + (f" Matched at IoU 0.3, a detection's centre sits a median {offset:.0f} px from its "
           "truth box's." if offset == offset else "")
        + " Data sets that label by projecting 3D boxes into the image give truth boxes that sit "
        "off the object, and annotations may leave real changes out: read AP50 here as a measure "
        "of the labels' geometry as much as of the detector, and compare rows at IoU 0.3 too."
    ]  # fmt: skip


def _no_pixel_warnings(t: pd.DataFrame) -> list[str]:
    """Method §13.3: a WARNING where a no-pixel baseline comes within 0.02 of the detector."""
    if "best_no_pixel" not in t.columns:
        return []
    det, out = t.iloc[0], []
    for r in t.iloc[2:].itertuples():
        if str(r.row).startswith("detector"):  # the detector itself, on a part of the frames
            continue
        gap = float(det["ap50_voc_all_point"]) - float(r.ap50_voc_all_point)
        if gap < 0.02:
            how = (
                "by the plain difference of the two images, without localizing anything, so the "
                "localizer adds little that a difference image does not"
                if str(r.row).startswith("plain difference")
                else "without reading a pixel (the confound Table I warns about), so the "
                "detector's AP says little about what it sees"
            )
            out.append(
                f"WARNING: {r.row} reaches AP50 {r.ap50_voc_all_point:.3f}, "
                + ("above" if gap < 0 else "within 0.02 of")
                + f" the detector's {det['ap50_voc_all_point']:.3f}: these boxes can be ranked "
                f"this well {how}."
            )
    if det["verdict"] == "baseline":
        out.append(
            f"WARNING: the detector is above chance but not clear of the best baseline row "
            f"({det['best_no_pixel']}; paired difference [{det['vs_no_pixel_ci_low']:+.3f}, "
            f"{det['vs_no_pixel_ci_high']:+.3f}]): no verdict above it (method §13.3)."
        )
    return out

"""``detect.html``: the change detector's page (method §13), self-contained beside its images.

The query trajectory over the map (``trajectory.png``), Table D where frames are annotated, and the
most changed places, each as query frame (change boxes in yellow) | the map frame it was paired
with | the LoC map overlay with its colour bar. Images are JPEG thumbnails under ``detect/``; the
page fetches nothing from the network.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.errors import HarnessError
from harness.imagestore import read_image
from harness.pairs.modes import PAIRING_MODES
from harness.records import FRAME_KEY
from harness.reports.alarm_words import alarm_words, in_words
from harness.reports.detect_figures import has_poses
from harness.reports.detect_notes import not_comparable_html, uncertain_html
from harness.reports.detect_run import DetectRun
from harness.reports.html import (  # the page reports its own loaded images (browser test)
    SCRIPT,
    esc,
)
from harness.reports.overlay import frame_drawn_boxes
from harness.reports.table_d import table_d_html
from harness.reports.table_dp import pixel_html
from harness.runtime.cache import write_text

CSS = (
    "body{font-family:system-ui,sans-serif;margin:1.5rem auto;max-width:1200px;color:#222}"
    "table{border-collapse:collapse;margin:.5rem 0}td,th{border:1px solid #ccc;padding:.25rem"
    " .5rem;text-align:right}th{background:#f4f4f4}td:first-child{text-align:left}"
    ".place{display:flex;gap:.6rem;align-items:flex-start;margin:.8rem 0;flex-wrap:wrap}"
    ".warn{background:#fff4d6;border-left:4px solid #e0a000;padding:.4rem .6rem}"
    ".place figure{margin:0}.place img{max-width:360px;border:1px solid #bbb}"
    "figcaption{font-size:.8rem;color:#555}.note{color:#555;font-size:.9rem}"
)


def _thumb(img: np.ndarray, path: Path, width: int = 360) -> str:
    h, w = img.shape[:2]
    if w > width:
        img = cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    elif w < 240:  # tiny frames (the fixture's): enlarged, pixels kept sharp
        up = int(np.ceil(240 / w))
        img = cv2.resize(img, (w * up, h * up), interpolation=cv2.INTER_NEAREST)
    path.parent.mkdir(exist_ok=True)
    cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    return f"{path.parent.name}/{path.name}"


def _top_box_exceedance(dets: pd.DataFrame, k: tuple[str, str, int]) -> float:
    """The calibrated score of a frame's first change box (NaN: none)."""
    b = dets[
        (dets["kind"] == "detection")
        & (dets["session"] == k[0])
        & (dets["camera"] == k[1])
        & (dets["utime"] == k[2])
    ]
    if not len(b) or "exceedance" not in b.columns:
        return float("nan")
    return float(b["exceedance"].min())


#: Annotated change frames shown on the page (detections in yellow, annotations in red).
ANNOTATED_SHOWN = 6


def _truth_boxes(ann: pd.DataFrame | None) -> dict[tuple[str, str, int], list[tuple]]:
    """The annotated change boxes of each frame."""
    out: dict[tuple[str, str, int], list[tuple]] = {}
    if ann is None or not len(ann):
        return out
    for r in ann[ann["status"] == "change"].itertuples():
        out.setdefault((str(r.session), str(r.camera), int(r.utime)), []).append(
            (r.x1, r.y1, r.x2, r.y2)
        )
    return out


def _query_thumb(
    out: Path,
    dets: pd.DataFrame,
    truth: dict[tuple[str, str, int], list[tuple]],
    k: tuple[str, str, int],
    image: str,
    file_name: str = "",
    alarmed: bool = True,
) -> tuple[str, str]:
    """(caption, thumbnail) of a query frame: detections in yellow, annotated changes in red.

    The caption names the frame by its file name where it has one (method §13.2). A frame whose
    calibrated score does not reach the alarm rate (``alarmed`` False, method §13.1) shows no
    change box: "no change detected".
    """
    q = read_image(image).copy()
    for x1, y1, x2, y2 in frame_drawn_boxes(dets, k) if alarmed else []:
        cv2.rectangle(q, (int(x1), int(y1)), (int(x2) - 1, int(y2) - 1), (255, 220, 0), 2)
    for x1, y1, x2, y2 in truth.get(k, []):
        cv2.rectangle(q, (int(x1), int(y1)), (int(x2) - 1, int(y2) - 1), (230, 30, 30), 1)
    what = "change boxes in yellow" if alarmed else "no change detected at the alarm rate"
    what += ", annotated changes in red" if k in truth else ""
    name = f"{k[0]}_{k[1]}_{k[2]}"
    label = file_name or f"{k[0]} {k[2]}"
    return (f"query {label} ({what})", _thumb(q, out / "detect" / f"{name}_q.jpg"))


def _figures(cells: list[tuple[str, str]]) -> str:
    return "".join(
        f'<figure><img src="{esc(src)}" alt="{esc(cap)}">'
        f"<figcaption>{esc(cap)}</figcaption></figure>"
        for cap, src in cells
    )


@dataclass(frozen=True)
class Places:
    """What every most-changed place of the page reads: the run's boxes, annotations, frames.

    ``dets``: the change boxes; ``truth``: the annotated boxes by frame; ``fk``: the frame table
    by frame key; ``maps``: the LoC overlays; ``against``: what the frame's and its top box's
    calibrated scores are shares of.
    """

    dets: pd.DataFrame
    truth: dict[tuple[str, str, int], list[tuple]]
    fk: pd.DataFrame
    maps: dict[tuple[str, str, int], Path]
    map_session: str
    against: tuple[str, str] = ("frames of this run", "candidate boxes")


def _place_html(out: Path, i: int, r: Any, c: Places) -> str:
    """One most-changed place: query frame | the map frame it was paired with | its LoC map."""
    dets, truth, fk, maps, map_session, against = (
        c.dets,
        c.truth,
        c.fk,
        c.maps,
        c.map_session,
        c.against,
    )
    k = (str(r.session), str(r.camera), int(r.utime))
    name = f"{k[0]}_{k[1]}_{k[2]}"
    q_name, m_name = str(getattr(r, "name", "") or ""), str(getattr(r, "r_name", "") or "")
    alarmed = bool(getattr(r, "alarmed", True))
    cells = [_query_thumb(out, dets, truth, k, str(r.image), q_name, alarmed)]
    mk = (map_session, str(r.r_camera), int(r.r_utime)) if r.r_utime == r.r_utime else None
    if mk is not None and mk in fk.index:
        mimg = read_image(str(fk.loc[mk, "image"]))
        m_label = m_name or f"{mk[0]} {mk[2]}"
        cells.append((f"map {m_label}", _thumb(mimg, out / "detect" / f"{name}_m.jpg")))
    if k in maps:
        bgr = cv2.imread(str(maps[k]))
        if bgr is None:
            raise HarnessError(f"{maps[k]}: this run's LoC overlay cannot be read back")
        over = bgr[..., ::-1]
        cells.append(
            (
                "change map: the likelihood of change (LoC) of each pixel, by rank fusion, with "
                "its colour bar",
                _thumb(over, out / "detect" / f"{name}_l.jpg"),
            )
        )
    where = f", at ({r.x:.1f}, {r.y:.1f}) m" if np.isfinite([r.x, r.y]).all() else ""
    title = esc(q_name) if q_name else f"{esc(k[0])} {esc(k[1])} {k[2]}"
    uncertain = (
        f' <span class="uncertain">(uncertain pair: confidence {r.pair_confidence:.2f})</span>'
        if getattr(r, "uncertain_pair", False)
        else ""
    )
    found = f"{int(r.boxes)} change boxes" if alarmed else "no change detected at the alarm rate"
    calibrated = (
        f"{esc(in_words(r.exceedance, against[0]))} (raw change score {r.score:.3g}, no unit)"
        if hasattr(r, "exceedance")
        else f"raw change score {r.score:.3g} (no unit)"
    )
    return (
        f'<h3 id="place{i}" data-alarmed="{int(alarmed)}">{i}. {title}: {calibrated}, '
        f"{found}{where}{uncertain}</h3>"
        + (
            f'<p class="note" data-calibrated="{r.exceedance:.6g}">Its top box: '
            f"{esc(in_words(_top_box_exceedance(dets, k), against[1]))}.</p>"
            if hasattr(r, "exceedance")
            else ""
        )
        + f'<div class="place" data-place="{i}">{_figures(cells)}</div>'
    )


def _annotated_html(
    out: Path,
    fr: pd.DataFrame,
    dets: pd.DataFrame,
    truth: dict[tuple[str, str, int], list[tuple]],
) -> str:
    """The annotated change frames, most changed first (up to ``ANNOTATED_SHOWN``)."""
    in_truth = [
        r for r in fr.sort_values(["score", "image_id"], ascending=[False, True]).itertuples()
        if (str(r.session), str(r.camera), int(r.utime)) in truth
    ]  # fmt: skip
    shown = in_truth[:ANNOTATED_SHOWN]
    if not shown:
        return ""
    annotated = "".join(
        "<figure><img src='{1}' alt='{0}'><figcaption>{0}</figcaption></figure>".format(
            *(esc(x) for x in _query_thumb(
                out, dets, truth, (str(r.session), str(r.camera), int(r.utime)), str(r.image),
                str(getattr(r, "name", "") or ""),
            ))
        )
        for r in shown
    )  # fmt: skip
    return (
        f'<h2 id="annotated">Annotated changes: {len(shown)} of the {len(in_truth)} annotated '
        "change frames, most changed first</h2><p class='note'>Detections in yellow, the "
        "annotated change boxes in red: where they meet, the boxes found the change.</p>"
        f'<div class="place" data-annotated="{len(shown)}">{annotated}</div>'
    )


def _trajectory_html(frames: pd.DataFrame, by: str = "retrieval") -> str:
    """Where the query frames are (poses), or, without poses, their scores in time order.

    The words say how the frames were paired (``[pairs] by``).
    """
    if has_poses(frames):
        return (
            '<h2 id="trajectory">Where</h2><img id="trajectory-map" src="trajectory.png" '
            'alt="query trajectory over the map, coloured by change score" style="max-width:760px">'
        )
    mode = PAIRING_MODES.get(by)
    says = mode.says if mode is not None and mode.says else f"its map frame by {by}"
    return (
        '<h2 id="trajectory">When</h2><p class="note">The sessions have no poses: each query '
        f"frame was paired with {esc(says)}, and the figure shows the change score along the "
        "query sequence.</p>"
        '<img id="trajectory-map" src="trajectory.png" alt="change score of each query frame '
        'in time order" style="max-width:760px">'
    )


def alignment_html(al: pd.DataFrame | None, shown: int = 10) -> str:
    """How the local localizer's pairs were aligned, and the frames it could not align."""
    if al is None or not len(al):
        return ""
    counts = al["align"].value_counts().sort_index()
    how = ", ".join(f"{k} {int(v)}" for k, v in counts.items() if k != "none")
    html = f"<p class='note' data-align='all'>Pairs aligned (method §13.3): {esc(how)}.</p>"
    bad = al[al["align"] == "none"]
    if len(bad):
        names = ", ".join(
            f"{r.q_session} {r.q_camera} {int(r.q_utime)}" for r in bad.head(shown).itertuples()
        )
        more = f" and {len(bad) - shown} more" if len(bad) > shown else ""
        html += (
            f"<p class='warn' data-align='none'>could not align {len(bad)} of {len(al)} pairs: "
            f"their frames carry no change score and no box, never a wrong one (alignment.csv): "
            f"{esc(names)}{more}.</p>"
        )
    return html


def write_detect_page(
    run: DetectRun,
    results: tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame],
    maps: dict[tuple[str, str, int], Path],
    tables: tuple[pd.DataFrame | None, pd.DataFrame | None],
    alarms: dict[str, Any],
) -> Path:
    """Write ``out/detect.html`` and its thumbnails; return the page's path.

    ``alarms``: ``detect.json``'s ``alarm`` (:class:`harness.detect.calibrate.Alarms`), the one
    count of alarms, said on the page as it is in the files.

    ``results``: the frame rows, the most changed of them and the boxes; ``maps``: the LoC maps
    of those; ``tables``: Table D and its pixel AP against masks (either None where there is
    none). The run's ``alignment`` holds the local localizer's pairs and how each was aligned
    (method §13.3); the page says how many could not be aligned, and which.

    Where a frame is annotated, its annotated change boxes are drawn in red beside the detections
    (yellow), and a section shows the annotated change frames (up to ``ANNOTATED_SHOWN``).
    """
    out, frames, map_session, localizers = run.p.out, run.frames, run.map_session, run.localizers
    fr, top, dets = results
    fk = frames.set_index(FRAME_KEY)
    truth = _truth_boxes(run.ann)
    against = (
        ("no-change null frames", "no-change null boxes")
        if run.null is not None
        else ("frames of this run", "candidate boxes")
    )
    places = [
        _place_html(out, i, r, Places(dets, truth, fk, maps, map_session, against))
        for i, r in enumerate(top.itertuples(), start=1)
    ]
    qs = sorted(set(fr["session"]))
    what = f"{', '.join(qs)} against the map {map_session}"
    folders = run.folders
    if folders:  # sessions of image folders: name the folders, not the sessions map and query
        what = f"{', '.join(folders[1:])} against the map {folders[0]}"
    page = (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<title>dbl-harness detect: {esc(what)}</title>"
        f"<style>{CSS}</style><script>{SCRIPT}</script></head><body>"
        f"<h1>What changed: {esc(what)}</h1>"
        f"<p class='note'>{len(fr)} query frames; localizer(s): {esc(', '.join(localizers))}; "
        "each frame's change score is the highest likelihood of change (LoC: how badly the "
        "frame's boxes localize in its map frame, fused over its proposals) of the frame: raw, "
        "with no unit; the calibrated score beside it says how often a pair with no change "
        "scores as high (docs/detect.md). Detections: detections.json (COCO results) with "
        "images.json; one row per frame: frames.csv.</p>"
        + _alarms_html(run, alarms)
        + alignment_html(run.alignment)
        + _trajectory_html(frames, run.cfg.pairs.by)
        + table_d_html(tables[0])
        + pixel_html(tables[1])
        + _annotated_html(out, fr, dets, truth)
        + f'<h2 id="places">The {len(top)} most changed places</h2>'
        + uncertain_html(fr)
        + not_comparable_html(fr)
        + "".join(places)
        + "</body></html>\n"
    )
    write_text(out / "detect.html", page)
    return out / "detect.html"


def _alarms_html(run: DetectRun, al: dict[str, Any]) -> str:
    """The alarms at the nominal rate and the null they are measured against, in words.

    ``al``: ``detect.json``'s ``alarm``, the count the files and the console hold.
    """
    cal: dict[str, Any] = run.null.record if run.null is not None else {"method": "within-run"}
    lines = alarm_words(al, cal).splitlines()
    how = ""
    if cal.get("construction") == "perturbed":
        lim = cal["limits"]
        how = (
            f" The null: {cal['pairs']} pairs, each a map frame against a perturbed copy of "
            f"itself ({cal['copies_per_map_frame']} copies of each at most; gain within ±"
            f"{lim['gain']:g}, offset ±{lim['offset']:g} grey levels, shift ±"
            f"{lim['shift']:g} of the frame, rotation ±{lim['rotation_deg']:g}°, scale ±"
            f"{lim['scale']:g}, blur up to {lim['blur']:g} of the longer side, JPEG quality "
            f"{lim['jpeg_quality']}-95)."
        )
    elif cal.get("construction") == "neighbours":
        how = (
            f" The null: {cal['pairs']} pairs, each a map frame against its neighbour in the "
            "map's own sequence (a static scene seen twice a moment apart)."
        )
    return (
        f"<p class='note' data-alarms='{al['frames']}' data-calibration='{esc(cal['method'])}' "
        f"data-alarm-boxes='{al['boxes']}'>"
        + " ".join(esc(x) for x in lines)
        + esc(how)
        + " See docs/decisions.md, <i>Calibrated alarms</i>.</p>"
    )

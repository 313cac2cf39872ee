"""The report page's figures: PR curves and the gallery of change maps.

Each gallery entry is query | reference | LoC map, with the map's colour bar under it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.errors import HarnessError
from harness.fusion.fuse import loc_map
from harness.imagestore import read_image
from harness.methods import FUSION_METHODS, METHOD_LABELS
from harness.records import FRAME_KEY, IMAGE_KEY
from harness.reports.html.cells import NAN, esc
from harness.reports.overlay import colour_bar
from harness.reports.plots import pr_figure
from harness.runtime.cache import atomic_path

#: Height of each panel of a gallery thumbnail, pixels.
THUMB_H = 200


def _draw_boxes(
    img: np.ndarray, boxes: np.ndarray, colour: tuple[int, int, int], width: int
) -> np.ndarray:
    out = img.copy()
    for x1, y1, x2, y2 in np.asarray(boxes, np.float64).reshape(-1, 4):
        cv2.rectangle(out, (round(x1), round(y1)), (round(x2) - 1, round(y2) - 1), colour, width)
    return out


def _panel(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    return cv2.resize(img, (max(1, round(w * THUMB_H / h)), THUMB_H), interpolation=cv2.INTER_AREA)


def thumbnail(
    query: np.ndarray, reference: np.ndarray, lmap: np.ndarray, change: np.ndarray, box: np.ndarray
) -> np.ndarray:
    """Query (change boxes red, the sample yellow) | reference | LoC map over the query.

    The brighter the map, the more changed.
    """
    lw = max(1, round(query.shape[0] / THUMB_H))
    q = _draw_boxes(_draw_boxes(query, change, (230, 40, 40), 2 * lw), box, (255, 215, 0), 2 * lw)
    valid = np.isfinite(lmap)
    if valid.any():
        lo, hi = np.nanmin(lmap), np.nanmax(lmap)
        norm = np.where(valid, (lmap - lo) / (hi - lo if hi > lo else 1.0), 0.0)
    else:
        norm = np.zeros(lmap.shape)
    heat = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]
    heat = np.where(
        valid[..., None],
        (0.7 * heat + 0.3 * query).astype(np.uint8),
        (0.35 * query).astype(np.uint8),
    )
    heat = _draw_boxes(_draw_boxes(heat, change, (230, 40, 40), 2 * lw), box, (255, 215, 0), 2 * lw)
    gap = np.full((THUMB_H, 6, 3), 255, np.uint8)
    top = np.hstack([_panel(q), gap, _panel(reference), gap, _panel(heat)])
    lo, hi = (float(np.nanmin(lmap)), float(np.nanmax(lmap))) if valid.any() else (NAN, NAN)
    bar = colour_bar(_panel(heat).shape[1], lo, hi)
    bottom = np.full((bar.shape[0], top.shape[1], 3), 255, np.uint8)
    bottom[:, -bar.shape[1] :] = bar
    return np.vstack([top, bottom])


def stratum(sob: float, edges: list[float]) -> str:
    """``[lo, hi)`` of the size stratum of a box of relative size ``sob`` (the last one closed)."""
    k = int(np.clip(np.searchsorted(edges, sob, side="right") - 1, 0, len(edges) - 2))
    close = "]" if k == len(edges) - 2 else ")"
    return f"SoB [{edges[k]:g}, {edges[k + 1]:g}{close}"


@dataclass(frozen=True)
class GalleryInputs:
    """What one gallery reads: where it writes, the split report's rows and the run's tables.

    ``fr``: frames by key; ``refs``: the reference of each query image; ``chg``: the change
    annotations; ``image``: a frame's pixels by key; ``tag``: ``S`` or ``I``; ``split_file``,
    ``edges``, ``stratified``: the split report, the size strata's edges, whether the labels
    are stratified.
    """

    out: Path
    rep: pd.DataFrame
    fr: pd.DataFrame
    refs: pd.DataFrame
    chg: pd.DataFrame
    image: Callable[[tuple], np.ndarray]
    tag: str
    split_file: Path
    edges: list[float] | None
    stratified: bool


def _example(g: GalleryInputs, r: Any, m: str, kind: str) -> tuple[str, str]:
    """One worst case of method ``m``: its thumbnail under ``out/report/`` and its figure.

    Returns the thumbnail's file name and the figure's HTML.
    """
    out, rep, fr, refs, chg, image, tag = g.out, g.rep, g.fr, g.refs, g.chg, g.image, g.tag
    split_file, edges, stratified = g.split_file, g.edges, g.stratified
    col = f"loc_{m}"
    qk = (r.q_session, r.q_camera, int(r.q_utime))
    rk = refs.loc[(r.q_session, r.q_camera, int(r.q_utime), r.r_session)]
    rkey = (r.r_session, rk["r_camera"], int(rk["r_utime"]))
    img = rep[
        (rep["q_session"] == r.q_session)
        & (rep["q_camera"] == r.q_camera)
        & (rep["q_utime"] == r.q_utime)
        & (rep["r_session"] == r.r_session)
        & rep[col].notna()
    ]
    w, h = int(fr.loc[qk, "width"]), int(fr.loc[qk, "height"])
    lmap = loc_map(
        img[["x1", "y1", "x2", "y2"]].to_numpy(np.float64),
        img[col].to_numpy(np.float64),
        w,
        h,
    )
    change = chg[
        (chg["session"] == r.q_session)
        & (chg["camera"] == r.q_camera)
        & (chg["utime"] == r.q_utime)
    ][["x1", "y1", "x2", "y2"]].to_numpy()
    thumb = thumbnail(image(qk), image(rkey), lmap, change, np.array([[r.x1, r.y1, r.x2, r.y2]]))
    name = f"{tag}_{m}_{'fp' if kind.startswith('false') else 'miss'}_{r.row}.jpg"
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(thumb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 82]
    )
    if not ok:
        raise HarnessError(f"{out / 'report' / name}: could not encode a thumbnail")
    with atomic_path(out / "report" / name) as tmp:
        tmp.write_bytes(buf.tobytes())
    return name, (
        f'<figure><img src="report/{esc(name)}" alt="{esc(kind)}" '
        f'loading="lazy"><figcaption><b>{esc(kind.split(":")[0])}</b>, LoC '
        f"{r.__getattribute__(col):.3g}, RoC {r.RoC:.2f}, SoB {r.SoB:.3f}"
        + (f" (stratum {esc(stratum(r.SoB, edges))})" if stratified and edges else "")
        + f", N {r.N}<br>{esc(r.q_session)} {int(r.q_utime)} vs "
        f"{esc(r.r_session)} ({esc(r.season_pair)}); <a "
        f'href="{esc(split_file.relative_to(out))}">{esc(split_file.name)}</a> '
        f"row {r.row}"
        "</figcaption></figure>"
    )


def _gallery_intro(split: str, n: int, stratified: bool) -> str:
    labels = (
        "Table S's labels: positive = at least RoC-min inside a change, negative = at most "
        "RoC-max, whatever the box's size; each example names its size stratum, the only "
        "boxes it was compared with"
        if stratified
        else "Table I's labels, where box size decides much of the label"
    )
    intro = (
        "<p class='note'>Per method, the negatives it scored highest (false positives) and "
        "the positives it scored lowest "
        f"(missed changes) under {esc(split)} ({labels}). Each: query with "
        "the annotated change (red) and the sample "
        "(yellow) | its reference | the method's LoC map over the query, with its colour bar "
        "(the map's range of that method's LoC in this image; brighter = more likely "
        "changed). Rows refer to the split "
        f"report. At most {n} of each per method (<code>[report] gallery</code>).</p>"
    )
    return intro


def gallery_html(
    out: Path,
    split_file: Path | None,
    n: int,
    run: tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame],
    label: str = "label_stratified",
    edges: list[float] | None = None,
    localizer: str | None = None,
) -> tuple[str, list[Path]]:
    """The highest-LoC false positives and lowest-LoC missed changes per method, as thumbnails.

    ``run``: the run's frames, annotations and ranks. ``label``: ``label_stratified`` (Table S's
    labels: RoC only; each example names its size stratum) or ``label`` (Table I's).
    """
    frames, ann, ranks = run
    stratified = label == "label_stratified"
    tag, anchor = ("S", "gallery") if stratified else ("I", "galleryI")
    if n <= 0 or split_file is None:
        return "", []
    rep = pd.read_parquet(split_file)
    rep = rep.reset_index(names="row")
    rep = rep[rep["proposal_method"] == "all"]
    if localizer is not None and "localizer" in rep.columns:
        rep = rep[rep["localizer"] == localizer]
    fr = frames.set_index(FRAME_KEY)
    refs = ranks.drop_duplicates(IMAGE_KEY).set_index(IMAGE_KEY)
    chg = ann[ann["status"] == "change"]
    cache: dict[tuple, np.ndarray] = {}

    def image(key: tuple) -> np.ndarray:
        if key not in cache:
            cache[key] = read_image(fr.loc[key, "image"])
        return cache[key]

    g = GalleryInputs(out, rep, fr, refs, chg, image, tag, split_file, edges, stratified)
    parts, written = [], []
    (out / "report").mkdir(exist_ok=True)
    for m in [m for m in FUSION_METHODS if f"loc_{m}" in rep.columns]:
        col = f"loc_{m}"
        lab = rep[(rep[label] >= 0) & rep[col].notna()]
        fps = lab[lab[label] == 0].sort_values([col, "row"], ascending=[False, True]).head(n)
        misses = lab[lab[label] == 1].sort_values([col, "row"], ascending=[True, True]).head(n)
        figs = []
        for kind, rows in (
            ("false positive: the highest LoC among negatives", fps),
            ("missed change: the lowest LoC among positives", misses),
        ):
            for r in rows.itertuples():
                name, fig = _example(g, r, m, kind)
                written.append(out / "report" / name)
                figs.append(fig)
        parts.append(
            f"<h3>{esc(METHOD_LABELS[m])}</h3><div "
            f'class="grid">{"".join(figs) or "<p class=note>no labelled samples</p>"}</div>'
        )
    intro = _gallery_intro(split_file.stem, n, stratified)
    heading = "h3" if not stratified else "h2"
    title = "Change maps: worst cases" + ("" if stratified else " under Table I's labels")
    return f'<{heading} id="{anchor}">{title}</{heading}>' + intro + "".join(parts), written


def pr_figure_html(out: Path, curves: pd.DataFrame, tag: str, title: str) -> tuple[str, list[Path]]:
    """One PR figure of Table I's six methods from ``curves`` (one split's, as written).

    ``curves``: rows of ``splits/pr_curves*.parquet`` (``fusion``, ``precision``, ``recall``).
    """
    have = set(curves["fusion"]) if len(curves) else set()
    parts = [
        curves.loc[curves["fusion"] == m, ["fusion", "precision", "recall"]]
        for m in FUSION_METHODS
        if m in have
    ]
    if not parts:
        return "<p class='note'>no positive in this split: no curve</p>", []
    path = pr_figure(pd.concat(parts, ignore_index=True), out / "report" / f"pr_{tag}.png", title)
    return (
        f'<figure><img src="report/{esc(path.name)}" alt="{esc(title)}">'
        f"<figcaption>{esc(title)}</figcaption></figure>",
        [path],
    )

"""``OUT/report.html``: one page to look at a run.

It leads with the fair comparison. In this order: run facts (config, data, localizer, versions,
time, counts and drops), localization quality, a legend, Table S (size-stratified) and Table P with
intervals, the paired comparisons, then under Table S's labels at the headline RoC-max
(``[report] headline_roc_max``) one PR figure, a heat map of AP per season pair and a gallery of
change maps (for each of the six methods the highest-LoC false positives and the lowest-LoC missed
changes, each as query | reference | LoC map with its colour bar, its size stratum named, linked to
its row in the split report); last, the paper's protocol (Table I) with its confound warning at its
head and, collapsed, its table, PR figure, heat map and gallery. A cell is green when its 95%
interval lies clear above the floor, grey when it holds the floor, red when it lies clear below.

Everything is read from the run directory, so ``harness report OUT`` rebuilds the page for an
existing run. The page is one HTML file with its images beside it under ``OUT/report/``
(thumbnails; the gallery is capped by ``[report] gallery``); it fetches nothing at view time. A
small inline script counts the images that loaded (``data-images-loaded`` on ``<body>``), which the
browser test reads.
"""

from __future__ import annotations

import html
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from .cache import atomic_path, write_text
from .errors import HarnessError
from .fusion import loc_map
from .imagestore import local_uri, read_image
from .methods import FUSION_METHODS, METHOD_LABELS
from .outdirs import read_run_record
from .reports import LOC_COLUMNS, TABLE_INTRO, pivot

log = logging.getLogger(__name__)

#: Height of each panel of a gallery thumbnail, pixels.
THUMB_H = 200

CSS = """
body { font-family: -apple-system, "Segoe UI", Roboto, Helvetica, Arial, sans-serif;
       margin: 0 auto; max-width: 1180px; padding: 1.5rem 2rem 4rem; color: #1d2330;
       line-height: 1.45; background: #fbfbfd; }
h1 { font-size: 1.7rem; margin-bottom: .2rem; }
h2 { margin-top: 2.4rem; border-bottom: 2px solid #d9dde6; padding-bottom: .25rem; }
h3 { margin-top: 1.6rem; } .sub { color: #5b6475; margin-top: 0; }
table { border-collapse: collapse; margin: .6rem 0 1rem; font-size: .88rem; background: #fff; }
th, td { border: 1px solid #d9dde6; padding: .28rem .55rem; text-align: right;
         white-space: nowrap; }
th { background: #eef1f6; } td:first-child, th:first-child { text-align: left; }
tr.sep td { background: #f4f5f8; font-style: italic; color: #5b6475; }
tr.floor td { background: #f7f7ef; color: #5b6475; }
.ci { color: #7a8394; font-size: .8em; }
.warn { background: #fff4d6; border-left: 4px solid #e0a100; padding: .5rem .8rem;
        margin: .6rem 0; }
.facts td { text-align: left; white-space: normal; } td.l { text-align: left; }
details summary { cursor: pointer; color: #2f5fb3; margin: .4rem 0; }
.facts td:first-child { font-weight: 600; color: #3b4456; }
.grid { display: flex; flex-wrap: wrap; gap: 1rem; }
.grid figure { margin: 0; background: #fff; border: 1px solid #d9dde6; padding: .4rem; }
figure img { display: block; max-width: 100%; }
figcaption { font-size: .78rem; color: #3b4456; margin-top: .3rem; max-width: 560px; }
.pr img { width: 360px; }
.legend { background: #fff; border: 1px solid #d9dde6; padding: .5rem .8rem; font-size: .85rem; }
.sw { display: inline-block; width: 1.4em; height: .9em; vertical-align: middle;
      border: 1px solid #bbb; margin: 0 .2em; }
td.diag { color: #7a8394; text-align: center; }
#protocol { margin-top: 3rem; }
.note { color: #5b6475; font-size: .85rem; }
code { background: #eef1f6; padding: 0 .25rem; border-radius: 3px; }
nav a { margin-right: .8rem; font-size: .9rem; }
"""

SCRIPT = """
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.body.setAttribute('data-images-total', String(imgs.length));
  document.body.setAttribute('data-images-loaded', String(ok));
  var tables = document.querySelectorAll('table[data-table]').length;
  document.body.setAttribute('data-tables', String(tables));
});
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(v: float, d: int = 2) -> str:
    return "NaN" if v != v else f"{v:.{d}f}"


NAN = float("nan")


def _diff_colour(lo: float, hi: float) -> str:
    """A paired difference's background: green when its interval lies above 0, red below."""
    return "#e3f4e1" if lo > 0 else "#fbe3e1" if hi < 0 else "#fff"


#: What a change-table cell says about its AP, from its 95% interval and the floor.
VERDICTS = {
    "above": "its interval lies clear above the floor: better than a random ranking",
    "holds": "its interval holds the floor: not told apart from a random ranking",
    "below": "its interval lies clear below the floor: worse than a random ranking",
    "none": "no interval (or no positive): the shade shows the distance from the floor only",
}


def verdict(ap: float, lo: float, hi: float, floor: float) -> tuple[str, str]:
    """(verdict, background) of one AP: green above the floor, grey on it, red below it.

    The decision is the interval's (``lo > floor``, ``hi < floor``, else it holds the floor); the
    shade grows with the distance of the AP from the floor, as a share of the room there is
    (1 - floor above it, floor below it). Without an interval the verdict is ``none`` and the
    colour is a pale version of the same scale.
    """
    if ap != ap or floor != floor:
        return "none", "#f0f0f0"
    up = ap >= floor
    room = (1.0 - floor) if up else floor
    t = float(np.clip(abs(ap - floor) / room if room > 0 else 0.0, 0.0, 1.0))
    green = (int(232 - 100 * t), int(246 - 40 * t), int(228 - 100 * t))
    red = (int(251 - 20 * t), int(228 - 110 * t), int(225 - 110 * t))
    if lo != lo or hi != hi:
        r, g, b = green if up else red
        r, g, b = (int(255 - (255 - v) * 0.5) for v in (r, g, b))
        return "none", f"rgb({r},{g},{b})"
    if lo > floor:
        return "above", "rgb({},{},{})".format(*green)
    if hi < floor:
        return "below", "rgb({},{},{})".format(*red)
    return "holds", "#e4e4e4"


LEGEND = (
    '<div class="legend" data-legend="floor"><b>How to read the colours.</b> '
    '<span class="sw" style="background:rgb(182,226,178)"></span> green: the AP\'s 95% interval '
    "lies clear above the table's floor (the AP of a random ranking), the darker the further; "
    '<span class="sw" style="background:#e4e4e4"></span> grey: the interval holds the floor, so '
    "this data cannot tell the method from chance; "
    '<span class="sw" style="background:rgb(241,163,160)"></span> red: clear below the floor. '
    "Paired differences: green or red when their interval is clear of 0, white when it holds 0. "
    "A cell without an interval is paler and decides nothing.</div>"
)


def _heat(v: float, floor: float = 0.0) -> str:
    """A background colour for AP: pale red at the floor (a random ranking) to green at 1."""
    if v != v:
        return "#f0f0f0"
    v = float(np.clip((v - floor) / (1 - floor) if floor == floor and floor < 1 else v, 0, 1))
    r, g, b = (
        (int(255 - 90 * v), int(215 + 25 * v), int(215 - 60 * v))
        if v >= 0.5
        else (250, int(205 + 40 * v), int(200 + 20 * v))
    )
    return f"rgb({r},{g},{b})"


def _change_table(
    summ: pd.DataFrame,
    table: str,
    methods: tuple[str, ...],
    warnings: list[str],
    who: str = "",
) -> str:
    ap, lo, hi = (pivot(summ, table, methods, v) for v in ("ap", "ci_low", "ci_high"))
    floor = pivot(summ, table, methods, "floor")
    cols = list(ap.columns)
    head = "".join(f"<th>{_e(f'{c:.2f}' if isinstance(c, float) else c)}</th>" for c in cols)
    ref = next((m for m in ("rank_fusion", "score_max") if m in floor.index), floor.index[0])
    rows, sep = [], False
    for m in ap.index:
        if m not in FUSION_METHODS and not sep:
            rows.append(
                f'<tr class="sep"><td colspan="{len(cols) + 1}">variants and baselines (the '
                "baselines read no pixel)</td></tr>"
            )
            sep = True
        cells = "".join(
            '<td data-verdict="{}" style="background:{}">'.format(
                *verdict(ap.loc[m, c], lo.loc[m, c], hi.loc[m, c], floor.loc[m, c])
            )
            + f"{_num(ap.loc[m, c])}"
            + (
                f' <span class="ci">[{_num(lo.loc[m, c])}, {_num(hi.loc[m, c])}]</span>'
                if lo.loc[m, c] == lo.loc[m, c]
                else ""
            )
            + "</td>"
            for c in cols
        )
        rows.append(f"<tr><td>{_e(METHOD_LABELS[m])}</td>{cells}</tr>")
    rows.append(
        '<tr class="floor"><td>floor (random ranking)</td>'
        + "".join(f"<td>{_num(floor.loc[ref, c])}</td>" for c in cols)
        + "</tr>"
    )
    title, intro = TABLE_INTRO[table]
    warn = "".join(f'<div class="warn">{_e(w)}</div>' for w in warnings)
    heading = "h3" if table == "I" else "h2"
    return (
        f'<{heading} id="table{table}">{_e(title + who)}</{heading}><p class="note">{_e(intro)} '
        "Cells: AP [95% bootstrap interval over query images]; colour: the interval against "
        "the floor (see the legend).</p>"
        f'<table data-table="{table}"><tr><th>AP</th>{head}</tr>{"".join(rows)}</table>{warn}'
    )


def _localization(loc: pd.DataFrame, radius: float, who: str = "") -> str:
    head = "".join(f"<th>{_e(lab)}</th>" for _, lab, _ in LOC_COLUMNS)

    def rows(df: pd.DataFrame) -> str:
        return "".join(
            f'<tr><td>{_e(r.proposals)}</td><td class="l">{_e(r.season_pair)}</td>'
            + "".join(
                f"<td>{int(getattr(r, c))}</td>"
                if d == 0
                else f"<td>{_num(float(getattr(r, c)), d)}</td>"
                for c, _, d in LOC_COLUMNS
            )
            + "</tr>"
            for r in df.itertuples(index=False)
        )

    table = f"<tr><th>proposals</th><th>season pair</th>{head}</tr>"
    return (
        f'<h2 id="localization">Localization quality{_e(who)}</h2><p class="note">'
        "Every change figure rests on these ranks. Ground truth: "
        f"the reference frames within {radius:g} m of the paired frame (the place). R@k: "
        "share of query subimages whose place "
        "ranks within the first k; median r: 0.5 is chance; clean: subimages of annotated "
        "frames with RoC &le; 0.05.</p>"
        f'<table data-table="localization">{table}{rows(loc[loc["season_pair"] == "all"])}</table>'
        "<details><summary>per season "
        f"pair</summary><table>{table}{rows(loc[loc['season_pair'] != 'all'])}</table></details>"
    )


def _heatmap(summ: pd.DataFrame, method: str, split: str) -> str:
    """Table I's AP of one method per season pair, at ``split``."""
    d = summ[
        (summ["table"] == "I")
        & (summ["proposals"] == "all")
        & (summ["season_pair"] != "all")
        & (summ["method"] == method)
        & (summ["split"] == split)
    ]
    if not len(d):
        return ""
    return _heat_table(
        d.set_index("season_pair")["ap"].to_dict(),
        d.set_index("season_pair")["positive_rate"].to_dict(),
        "heatmapI",
        f"{METHOD_LABELS[method]}, Table I (the paper's protocol), {split}",
    )


def headline_split(out: Path, headline: float) -> Path | None:
    """The split report at the headline RoC-max (else the largest one written)."""
    files = sorted((out / "splits").glob("roc_max_*.parquet"))
    want = out / "splits" / f"roc_max_{headline:.2f}.parquet"
    return want if want in files else (files[-1] if files else None)


def _pr_figure(
    out: Path, rep: pd.DataFrame, label: str, tag: str, title: str
) -> tuple[str, list[Path]]:
    """One PR figure of the six methods on ``rep``'s ``label`` column (proposals = all)."""
    from .metrics import pr_curve
    from .plots import pr_figure

    allp = rep[(rep["proposals"] == "all") & (rep[label] >= 0)]
    curves = []
    for m in FUSION_METHODS:
        col = f"loc_{m}"
        if col not in allp.columns:
            continue
        sel = allp[col].notna()
        y = allp.loc[sel, label].to_numpy() == 1
        if y.any():
            _, prec, rec = pr_curve(y, allp.loc[sel, col].to_numpy())
            curves.append(pd.DataFrame({"method": m, "precision": prec, "recall": rec}))
    if not curves:
        return "<p class='note'>no positive in this split: no curve</p>", []
    path = pr_figure(pd.concat(curves), out / "report" / f"pr_{tag}.png", title)
    return (
        f'<figure><img src="report/{_e(path.name)}" alt="{_e(title)}">'
        f"<figcaption>{_e(title)}</figcaption></figure>",
        [path],
    )


def _heatmap_stratified(rep: pd.DataFrame, method: str, edges: list[float], split: str) -> str:
    """Table S's AP of one method per season pair (query season down, reference across)."""
    from .metrics import stratified_ap

    col = f"loc_{method}"
    allp = rep[(rep["proposals"] == "all") & (rep["label_stratified"] >= 0)]
    if col not in allp.columns or not len(allp):
        return ""
    pairs, floors = {}, {}
    for pair, g in allp.groupby("season_pair", sort=True):
        g = g[g[col].notna()]
        pairs[pair], floors[pair] = stratified_ap(
            g["label_stratified"].to_numpy() == 1, g[col].to_numpy(), g["SoB"].to_numpy(), edges
        )
    return _heat_table(
        pairs,
        floors,
        "heatmap",
        f"{METHOD_LABELS[method]}, Table S (size-stratified), {split}",
    )


def _heat_table(pairs: dict[str, float], floors: dict[str, float], anchor: str, what: str) -> str:
    seasons = sorted(
        {p.split("->")[0] for p in pairs} | {p.split("->")[1] for p in pairs},
        key=lambda s: ["WI", "SP", "SU", "AU"].index(s) if s in ("WI", "SP", "SU", "AU") else 9,
    )
    head = "".join(f"<th>{_e(s)}</th>" for s in seasons)

    def cell(q: str, r: str) -> str:
        if q == r:
            return '<td class="diag">&mdash;</td>'
        key = f"{q}->{r}"
        if key not in pairs:
            return '<td class="diag">no pair</td>'
        ap, fl = pairs[key], floors.get(key, NAN)
        colour = verdict(ap, NAN, NAN, fl)[1]
        text = _num(ap) if ap == ap else "NaN"
        return f'<td style="background:{colour}" title="floor {_num(fl)}">{text}</td>'

    rows = "".join(
        f"<tr><th>{_e(q)}</th>" + "".join(cell(q, r) for r in seasons) + "</tr>" for q in seasons
    )
    return (
        f'<h3 id="{anchor}">AP per season pair</h3><p class="note">{_e(what)}; query season '
        "down, reference season across. &mdash;: a season is never paired with itself; NaN: "
        "the pair has no positive (or no stratum with both labels); no pair: no query of that "
        "season found a reference of the other. A per-pair AP has no interval (few query "
        "images per pair): its colour is the pale scale of the legend and decides nothing "
        "(hover a cell for its floor).</p>"
        f'<table data-table="{anchor}"><tr><th>query \\ reference</th>{head}</tr>{rows}</table>'
    )


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


def _thumbnail(
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


def colour_bar(width: int, lo: float, hi: float, height: int = 30) -> np.ndarray:
    """The LoC map's colour scale: the inferno ramp from ``lo`` (left) to ``hi``, labelled.

    The map is normalised per image, so the bar states that image's range of the method's LoC.
    """
    ramp = np.linspace(0, 255, max(width, 2)).astype(np.uint8)[None, :].repeat(12, 0)
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_INFERNO)[..., ::-1]
    out = np.full((height, width, 3), 255, np.uint8)
    out[2:14] = bar[:, :width]
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.38
    left = f"LoC {lo:.3g}" if lo == lo else "no LoC"
    right = f"{hi:.3g} (more changed)" if hi == hi else ""
    cv2.putText(out, left, (1, height - 4), font, scale, (40, 40, 40), 1, cv2.LINE_AA)
    (tw, _), _ = cv2.getTextSize(right, font, scale, 1)
    cv2.putText(out, right, (max(1, width - tw - 1), height - 4), font, scale, (40, 40, 40), 1)
    return out


def _gallery(
    out: Path,
    split_file: Path | None,
    n: int,
    frames: pd.DataFrame,
    ann: pd.DataFrame,
    ranks: pd.DataFrame,
    label: str = "label_stratified",
    edges: list[float] | None = None,
    localizer: str | None = None,
) -> tuple[str, list[Path]]:
    """The highest-LoC false positives and lowest-LoC missed changes per method, as thumbnails.

    ``label``: ``label_stratified`` (Table S's labels: RoC only; each example names its size
    stratum) or ``label`` (Table I's).
    """
    stratified = label == "label_stratified"
    tag, anchor = ("S", "gallery") if stratified else ("I", "galleryI")
    if n <= 0 or split_file is None:
        return "", []
    rep = pd.read_parquet(split_file)
    rep = rep.reset_index(names="row")
    rep = rep[rep["proposals"] == "all"]
    if localizer is not None and "localizer" in rep.columns:
        rep = rep[rep["localizer"] == localizer]
    fr = frames.set_index(["session", "camera", "utime"])
    refs = ranks.drop_duplicates(["q_session", "q_camera", "q_utime", "r_session"]).set_index(
        ["q_session", "q_camera", "q_utime", "r_session"]
    )
    chg = ann[ann["status"] == "change"]
    cache: dict[tuple, np.ndarray] = {}

    def image(key: tuple) -> np.ndarray:
        if key not in cache:
            cache[key] = read_image(fr.loc[key, "image"])
        return cache[key]

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
                thumb = _thumbnail(
                    image(qk), image(rkey), lmap, change, np.array([[r.x1, r.y1, r.x2, r.y2]])
                )
                name = f"{tag}_{m}_{'fp' if kind.startswith('false') else 'miss'}_{r.row}.jpg"
                ok, buf = cv2.imencode(
                    ".jpg", cv2.cvtColor(thumb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 82]
                )
                if not ok:
                    raise HarnessError(f"{out / 'report' / name}: could not encode a thumbnail")
                with atomic_path(out / "report" / name) as tmp:
                    tmp.write_bytes(buf.tobytes())
                written.append(out / "report" / name)
                figs.append(
                    f'<figure><img src="report/{_e(name)}" alt="{_e(kind)}" '
                    f'loading="lazy"><figcaption><b>{_e(kind.split(":")[0])}</b>, LoC '
                    f"{r.__getattribute__(col):.3g}, RoC {r.RoC:.2f}, SoB {r.SoB:.3f}"
                    + (f" (stratum {_e(_stratum(r.SoB, edges))})" if stratified and edges else "")
                    + f", N {r.N}<br>{_e(r.q_session)} {int(r.q_utime)} vs "
                    f"{_e(r.r_session)} ({_e(r.season_pair)}); <a "
                    f'href="{_e(split_file.relative_to(out))}">{_e(split_file.name)}</a> '
                    f"row {r.row}"
                    "</figcaption></figure>"
                )
        parts.append(
            f"<h3>{_e(METHOD_LABELS[m])}</h3><div "
            f'class="grid">{"".join(figs) or "<p class=note>no labelled samples</p>"}</div>'
        )
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
        f"(missed changes) under {_e(split_file.stem)} ({labels}). Each: query with "
        "the annotated change (red) and the sample "
        "(yellow) | its reference | the method's LoC map over the query, with its colour bar "
        "(the map's range of that method's LoC in this image; brighter = more likely "
        "changed). Rows refer to the split "
        f"report. At most {n} of each per method (<code>[report] gallery</code>).</p>"
    )
    heading = "h3" if not stratified else "h2"
    title = "Change maps: worst cases" + ("" if stratified else " under Table I's labels")
    return f'<{heading} id="{anchor}">{title}</{heading}>' + intro + "".join(parts), written


def _stratum(sob: float, edges: list[float]) -> str:
    """``[lo, hi)`` of the size stratum of a box of relative size ``sob`` (the last one closed)."""
    k = int(np.clip(np.searchsorted(edges, sob, side="right") - 1, 0, len(edges) - 2))
    close = "]" if k == len(edges) - 2 else ")"
    return f"SoB [{edges[k]:g}, {edges[k + 1]:g}{close}"


def _table_l(out: Path) -> str:
    """Table L (SPEC section 11) from ``tableL.csv``: every AP coloured against its floor."""
    from .leaderboard import AP_COLUMNS

    t = pd.read_csv(out / "tableL.csv")
    first = str(t["localizer"].iloc[0])
    head = "".join(
        f"<th>{_e(h)}</th>"
        for h in (
            "localizer",
            "R@1",
            "R@5",
            *(h for *_, h in AP_COLUMNS),
            f"S rank fusion - {first}",
        )
    )
    rows = []
    for _, r in t.iterrows():
        cells = [f"<td>{_e(r['localizer'])}</td>"]
        cells += [f"<td>{_num(float(r[c]))}</td>" for c in ("recall_at_1", "recall_at_5")]
        for pfx, *_ in AP_COLUMNS:
            v, lo, hi, fl = (float(r[f"{pfx}_{k}"]) for k in ("ap", "ci_low", "ci_high", "floor"))
            cells.append(
                '<td data-verdict="{}" style="background:{}">'.format(*verdict(v, lo, hi, fl))
                + _num(v)
                + (f' <span class="ci">[{_num(lo)}, {_num(hi)}]</span>' if lo == lo else "")
                + "</td>"
            )
        d, dl, dh = (
            float(r[f"S_rank_fusion_{k}"]) for k in ("diff", "diff_ci_low", "diff_ci_high")
        )
        cells.append(
            "<td></td>"
            if d != d
            else f'<td style="background:{_diff_colour(dl, dh)}">{d:+.2f} '
            f'<span class="ci">[{dl:+.2f}, {dh:+.2f}]</span></td>'
        )
        rows.append("<tr>" + "".join(cells) + "</tr>")
    r0 = t.iloc[0]
    rows.append(
        f'<tr class="floor"><td>floor ({_e(first)})</td><td></td><td></td>'
        + "".join(f"<td>{_num(float(r0[f'{p}_floor']))}</td>" for p, *_ in AP_COLUMNS)
        + "<td></td></tr>"
    )
    return (
        '<h2 id="tableL">Table L: localizers</h2><p class="note">One row per localizer and '
        "one for all localizers fused by rank (SPEC section 11), every one scored on the same "
        f"query images. Table S at RoC-max {float(t['roc_max'].iloc[0]):.2f}; each AP with its "
        "95% interval, coloured against its own floor (a random ranking of the same samples); "
        f"the last column is the paired difference from {_e(first)} in Table S rank fusion over "
        "the same bootstrap resamples. Recall: the ground-truth place ranked first (R@1) or in "
        f'the first five (R@5).</p><table data-table="L"><tr>{head}</tr>{"".join(rows)}</table>'
    )


def _other_blocks(summ: pd.DataFrame, names: list[str], warnings: dict[str, list[str]]) -> str:
    """Tables S and P of every localizer after the first, and of ``all localizers``."""
    parts = []
    for name in names:
        s = summ[summ["localizer"] == name]
        methods = tuple(m for m in METHOD_LABELS if m in set(s["method"]))
        pre = f"[{name}] "
        for t in ("S", "P"):
            notes = [w[len(pre) :] for w in warnings.get(t, []) if w.startswith(pre)]
            html = _change_table(s, t, methods, notes, f" (localizer: {name})")
            parts.append(html.replace(f'id="table{t}"', f'data-localizer="{_e(name)}"', 1))
    return (
        '<h2 id="blocks">Tables S and P of the other localizers</h2>'
        "<p class='note'>The same tables, each localizer's boxes alone; <i>all localizers</i>: "
        "every localizer's boxes fused by rank (no score method is defined across "
        "localizers).</p>" + "".join(parts).replace("<h2 ", "<h3 ").replace("</h2>", "</h3>")
    )


def write_html_report(out: Path, gallery: int | None = None) -> Path:
    """Write ``out/report.html`` (and its images under ``out/report/``) for a finished run.

    Raises:
        HarnessError: ``out`` holds no finished run (no ``run.json``).
    """
    from .annotations import load_annotations

    out = Path(out)
    run: dict[str, Any] = read_run_record(out)
    cfg = run["config"]
    n = int(cfg["report"].get("gallery", 3)) if gallery is None else gallery
    summ_all = pd.read_parquet(out / "splits" / "summary.parquet")
    loc = pd.read_csv(out / "localization.csv")
    ranks = pd.read_parquet(out / "ranks.parquet")
    names = list(dict.fromkeys(summ_all["localizer"].astype(str)))
    lead_name = names[0]  # with several localizers the sections below show the first one's
    multi = len(names) > 1
    summ = summ_all[summ_all["localizer"] == lead_name] if multi else summ_all
    if multi:
        loc = loc[loc["localizer"] == lead_name]
        ranks = ranks[ranks["localizer"] == lead_name]
    frames = pd.read_parquet(out / "cache" / "frames" / run["keys"]["frames"] / "frames.parquet")
    frames["image"] = [local_uri(u, out, Path(cfg["data_root"])) for u in frames["image"]]
    ann = load_annotations(Path(cfg["annotations"]))
    methods = tuple(m for m in METHOD_LABELS if m in set(summ["method"]))
    warnings = run.get("warnings", {})
    if multi:  # the first block's lines (the record prefixes each with its block's name)
        pre = f"[{lead_name}] "
        warnings = {
            t: [w[len(pre) :] for w in ws if w.startswith(pre)] for t, ws in warnings.items()
        }
    counts = run["counts"]
    locs = [x for x in run.get("localizers") or [] if isinstance(x, dict)] or [
        {"name": cfg.get("descriptor", {}).get("name", "?"), "kind": "descriptor"}
    ]
    loc_name = ", ".join(str(x.get("name")) for x in locs)
    localizer_facts = "; ".join(
        f"{x.get('name')}: "
        + (
            f"imported from {x.get('file')} (sha256 {x.get('sha256')}, scores as "
            f"{x.get('score_kind')})"
            if x.get("kind") == "import"
            else f"bag of visual words ({x.get('bovw', {}).get('features')}, k = "
            f"{x.get('bovw', {}).get('k')})"
            if x.get("kind") == "bovw"
            else "built-in descriptor "
            + str(x.get("descriptor") or cfg.get("descriptor", {}).get("name"))
        )
        + (f", proposals {', '.join(x['proposals'])}" if x.get("proposals") else "")
        for x in locs
    )
    drops = {
        s: ", ".join(f"{k} {v}" for k, v in d.get("dropped", {}).items() if v)
        for s, d in run.get("ingest", {}).items()
    }
    facts = [
        ("config", f"{cfg['name']} ({len(cfg['sessions'])} sessions)"),
        ("data root", cfg["data_root"]),
        ("annotations", cfg["annotations"]),
        ("versions", ", ".join(f"{k} {v}" for k, v in run["versions"].items() if k != "platform")),
        ("platform", run["versions"].get("platform", "")),
        ("executor", ", ".join(f"{k} {v}" for k, v in run.get("executor", {}).items())),
        (
            "time",
            f"{run['total_s']:.1f} s: "
            + ", ".join(f"{k} {v:.1f}" for k, v in run["timings_s"].items()),
        ),
        (
            "counts",
            (
                f"{counts['frames']} frames, {counts['annotated_frames']} annotated frames, "
                f"{counts['pairs']} pairs (query images), "
                f"{counts['ranked_subimages']} ranked subimages, {counts['samples']} samples"
            ),
        ),
        ("dropped at ingest", "; ".join(f"{s}: {d}" for s, d in drops.items() if d) or "nothing"),
        ("localizer", localizer_facts),
        (
            "ranking",
            "; ".join(
                f"{s}: {', '.join(f'{k} {v}' for k, v in c.items() if v)}"
                if isinstance(c, dict)
                else f"{s} {c}"
                for s, c in (counts.get("rank_counts") or {}).items()
            ),
        ),
    ]
    fact_rows = "".join(f"<tr><td>{_e(k)}</td><td>{_e(v)}</td></tr>" for k, v in facts)
    who = f" (localizer: {lead_name}; data: {Path(str(cfg['data_root'])).name})"
    cmp_rows = summ[
        (summ["proposals"] == "all") & (summ["season_pair"] == "all") & summ["diff"].notna()
    ]
    cmp_html = ""
    for table in ("S", "P", "I"):  # the fair tables first, the paper's protocol last
        t = cmp_rows[cmp_rows["table"] == table]
        if not len(t):
            continue
        d = t.pivot(index="method", columns="split", values="diff").reindex(
            [m for m in methods if m in set(t["method"])]
        )
        lo = t.pivot(index="method", columns="split", values="diff_ci_low").reindex(d.index)
        hi = t.pivot(index="method", columns="split", values="diff_ci_high").reindex(d.index)
        cols = [c for c in t["split"].drop_duplicates()]
        head = "".join(f"<th>{_e(c)}</th>" for c in cols)
        diffs = "".join(
            f"<tr><td>{_e(METHOD_LABELS[m])} &minus; rank fusion</td>"
            + "".join(
                f'<td style="background:{_diff_colour(lo.loc[m, c], hi.loc[m, c])}">'
                f"{d.loc[m, c]:+.2f} "
                f'<span class="ci">[{lo.loc[m, c]:+.2f}, {hi.loc[m, c]:+.2f}]</span></td>'
                for c in cols
            )
            + "</tr>"
            for m in d.index
        )
        cmp_html += (
            f"<h3>{_e(TABLE_INTRO[table][0])}</h3><table "
            f'data-table="cmp{table}"><tr><th>difference</th>{head}</tr>{diffs}</table>'
        )
    headline = float(cfg["report"].get("headline_roc_max", 0.05))
    split_file = headline_split(out, headline)
    split_name = split_file.stem if split_file is not None else ""
    edges = [float(e) for e in cfg["splits"]["sob_strata"]]
    (out / "report").mkdir(exist_ok=True)
    rep = pd.read_parquet(split_file) if split_file is not None else None
    if rep is not None and multi:
        rep = rep[rep["localizer"] == lead_name]
    lead = "rank_fusion" if "rank_fusion" in methods else methods[0]
    pr_s, pr_files = (
        _pr_figure(out, rep, "label_stratified", "S", f"Table S labels (RoC only), {split_name}")
        if rep is not None
        else ("", [])
    )
    pr_i, pr_files_i = (
        _pr_figure(out, rep, "label", "I", f"Table I labels (the paper's), {split_name}")
        if rep is not None
        else ("", [])
    )
    heat_s = _heatmap_stratified(rep, lead, edges, split_name) if rep is not None else ""
    only = lead_name if multi else None
    gallery_s, thumbs = _gallery(
        out, split_file, n, frames, ann, ranks, "label_stratified", edges, only
    )
    # the paper's protocol is collapsed at the end: one example per method and kind is enough there
    gallery_i, thumbs_i = _gallery(
        out, split_file, min(n, 1), frames, ann, ranks, "label", edges, only
    )
    keep = {p.resolve() for p in [*thumbs, *thumbs_i, *pr_files, *pr_files_i]}
    for p in (out / "report").glob("*") if (out / "report").is_dir() else []:
        if p.suffix in (".jpg", ".png") and p.resolve() not in keep:
            p.unlink()  # images of an earlier page that this page no longer shows
    confound = [w for w in warnings.get("I", []) if w.startswith("WARNING")]
    notes_i = [w for w in warnings.get("I", []) if not w.startswith("WARNING")]
    protocol = (
        '<h2 id="protocol">The paper\'s protocol (Table I): read it last</h2>'
        "<p class='note'>Table I labels a box positive when it is at least 90% inside a change "
        "<i>and</i> at most 40% of the image, negative when it is at most RoC-max changed "
        "<i>and</i> at least 40% of the image: box size alone can separate the labels, so its "
        "APs measure box size as much as change. It is here to compare with the paper's "
        "numbers, not to compare detectors (Table S does that).</p>"
        + "".join(f'<div class="warn">{_e(w)}</div>' for w in confound)
        + "<details><summary>Table I, its PR curve, AP per season pair and worst cases "
        "under its labels</summary>"
        + _change_table(summ, "I", methods, notes_i, who)
        + f'<div class="grid pr" id="prI">{pr_i}</div>'
        + _heatmap(summ, lead, split_name)
        + gallery_i
        + "</details>"
    )
    body = [
        f"<h1>Detection-by-Localization: {_e(cfg['name'])}, localizer {_e(loc_name)}</h1>",
        (
            f"<p class='sub'>data: {_e(cfg['data_root'])}; dbl-harness "
            f"{_e(run['versions'].get('dbl-harness', ''))}, seed {run['seed']}</p>"
        ),
        "<nav>"
        + "".join(
            f'<a href="#{a}">{t}</a>'
            for a, t in (
                ("facts", "run"),
                ("localization", "localization"),
                *([("tableL", "Table L"), ("blocks", "per localizer")] if multi else []),
                ("tableS", "Table S"),
                ("tableP", "Table P"),
                ("comparisons", "comparisons"),
                ("pr", "PR curve"),
                ("heatmap", "season pairs"),
                ("gallery", "change maps"),
                ("protocol", "Table I (paper's protocol)"),
            )
        )
        + "</nav>",
        f'<h2 id="facts">Run</h2><table class="facts" data-table="facts">{fact_rows}</table>',
        _localization(loc, float(cfg["retrieval"]["gt_radius_m"]), who),
        LEGEND,
        _table_l(out) if multi else "",
        _other_blocks(summ_all, names[1:], run.get("warnings", {})) if multi else "",
        (
            f"<p class='note'>The sections below show localizer {_e(lead_name)}, the first of "
            f"{len(names) - 1}; the others' Tables S and P are above, every table of every "
            "localizer in tableS.md, tableP.md, table1.md.</p>"
            if multi
            else ""
        ),
        *(_change_table(summ, t, methods, warnings.get(t, []), who) for t in ("S", "P")),
        '<h2 id="comparisons">Paired comparisons with rank fusion</h2><p '
        'class="note">AP(method) &minus; AP(rank fusion) over the same '
        "bootstrap resamples of query images, with its 95% interval; green: better than "
        "rank fusion, red: worse, white: cannot be told apart "
        "on this data.</p>" + cmp_html,
        (
            f'<h2 id="pr">Precision-recall curve (Table S labels, {_e(split_name)})</h2>'
            "<p class='note'>The six methods' curves over the samples of all size strata "
            "pooled (Table S's AP is the mean of the per-stratum APs, weighted by positives). "
            "The other RoC-max splits: <code>plots/pr_*.png</code>.</p>"
            f'<div class="grid pr">{pr_s}</div>'
        ),
        heat_s,
        gallery_s,
        protocol,
    ]
    page = (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><meta name='viewport' "
        "content='width=device-width, initial-scale=1'>"
        "<title>dbl-harness report: "
        f"{_e(cfg['name'])}, localizer {_e(loc_name)}</title>"
        f"<style>{CSS}</style><script>{SCRIPT}</script></head><body>"
        + "\n".join(body)
        + "</body></html>\n"
    )
    write_text(out / "report.html", page)
    log.info("report: wrote %s", out / "report.html")
    return out / "report.html"

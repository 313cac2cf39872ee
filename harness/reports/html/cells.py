"""The report page's tables as HTML: verdicts, change tables, localization, heat maps, Table L.

Every table reads the same specs as the markdown (:mod:`harness.reports.change`); a cell
is green when its 95% interval lies clear above the floor, grey when it holds it, red below.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.evaluate.chance import few_text
from harness.methods import METHOD_LABELS
from harness.reports import tables as report_tables
from harness.reports.change import ChangeTable, change_table, column_label
from harness.reports.leaderboard import COST_NOTE, WHY, LCell, leader_table
from harness.reports.render import loc_columns
from harness.runtime.costs import COST_COLUMNS


def esc(x: Any) -> str:
    """``x`` as HTML text."""
    return html.escape(str(x))


def num(v: float, d: int = 2) -> str:
    """``v`` to ``d`` decimals; NaN as ``NaN``."""
    return "NaN" if v != v else f"{v:.{d}f}"


NAN = float("nan")


def diff_colour(lo: float, hi: float) -> str:
    """A paired difference's background: green when its interval lies above 0, red below."""
    return "#e3f4e1" if lo > 0 else "#fbe3e1" if hi < 0 else "#fff"


#: What a change-table cell says about its AP: method §9's verdict
# (:func:`harness.evaluate.chance.verdict`).
VERDICTS = {
    "above": "above chance: above the chance band and clear of the random baseline (paired)",
    "chance": "cannot be told from chance on this data",
    "below": "below chance: under the chance band and clear below the random baseline (paired)",
    "untested": "no interval: not tested against chance; the shade shows the distance only",
    "undefined": "undefined (no positive)",
    "few": "too few query images hold a positive for a verdict (method §9): no colour",
}


#: An AP cell's opening tag: its verdict and background (:func:`verdict_colour`).
TD_VERDICT = '<td data-verdict="{}" style="background:{}">'


def verdict_colour(ap: float, floor: float, word: str) -> tuple[str, str]:
    """(verdict, background) of one AP cell: the colour of method §9's verdict ``word``.

    Green above chance, red below, grey when it cannot be told from chance; the shade grows with
    the distance of the AP from the floor, as a share of the room there is (1 - floor above it,
    floor below it). Untested cells (no interval) get a pale version of the same scale and decide
    nothing.
    """
    if ap != ap or floor != floor or word == "undefined":
        return "undefined", "#f0f0f0"
    if word == "few":  # evidence before a verdict (method §9): no colour at all
        return "few", "#ffffff"
    up = ap >= floor
    room = (1.0 - floor) if up else floor
    t = float(np.clip(abs(ap - floor) / room if room > 0 else 0.0, 0.0, 1.0))
    green = (int(232 - 100 * t), int(246 - 40 * t), int(228 - 100 * t))
    red = (int(251 - 20 * t), int(228 - 110 * t), int(225 - 110 * t))
    if word == "above":
        return "above", "rgb({},{},{})".format(*green)
    if word == "below":
        return "below", "rgb({},{},{})".format(*red)
    if word == "chance":
        return "chance", "#e4e4e4"
    r, g, b = green if up else red
    r, g, b = (int(255 - (255 - v) * 0.5) for v in (r, g, b))
    return "untested", f"rgb({r},{g},{b})"


LEGEND = (
    '<div class="legend" data-legend="floor"><b>How to read the colours</b> (method §9, one rule '
    "for every colour). "
    '<span class="sw" style="background:rgb(182,226,178)"></span> green: above chance, the AP '
    "exceeds the chance band (the 95th percentile of random orders of the same samples) and its "
    "paired bootstrap difference from the random baseline lies clear above 0, the darker the "
    "further from the floor; "
    '<span class="sw" style="background:#e4e4e4"></span> grey: this data cannot tell the method '
    "from chance; "
    '<span class="sw" style="background:rgb(241,163,160)"></span> red: below chance, '
    "symmetrically. The floor is the mean AP of those random orders, not the positive rate. "
    "Paired differences: green or red when their interval is clear of 0, white when it holds 0. "
    'A cell without an interval is paler and decides nothing. A white cell saying "too few '
    'positives (n)" rests on fewer query images holding a positive than [report] '
    "min_positive_images (or on a bootstrap that cannot vary it): it has no verdict.</div>"
)


def change_html(t: ChangeTable, who: str = "") -> str:
    """One change table (I, S or P), its cells coloured by method §9's verdict against the floor."""
    spec, cols = t.spec, t.columns
    head = "".join(f"<th>{esc(column_label(c))}</th>" for c in cols)
    rows, sep = [], False
    for r in t.rows:
        if r.extra and not sep:
            rows.append(
                f'<tr class="sep"><td colspan="{len(cols) + 1}">variants and baselines (the '
                "baselines read no pixel)</td></tr>"
            )
            sep = True
        cells = "".join(
            '<td data-verdict="{}" style="background:{}" title="{}">'.format(
                *verdict_colour(ap, floor, str(ver)), esc(VERDICTS.get(str(ver), ""))
            )
            + f"{num(ap)}"
            + (f' <span class="ci">[{num(lo)}, {num(hi)}]</span>' if lo == lo else "")
            + (f' <span class="few">{esc(few_text(int(n)))}</span>' if ver == "few" else "")
            + "</td>"
            for ap, lo, hi, floor, ver, n in zip(
                r.ap, r.low, r.high, r.floor, r.verdict, r.positive_images, strict=True
            )
        )
        rows.append(f"<tr><td>{esc(r.label)}</td>{cells}</tr>")
    rows += [
        f'<tr class="floor"><td>{esc(label)}</td>'
        + "".join(f"<td>{esc(v)}</td>" for v in vals)
        + "</tr>"
        for label, vals in t.chance
    ]
    warn = "".join(f'<div class="warn">{esc(w)}</div>' for w in (*t.notes, *t.warnings))
    heading = "h3" if spec.collapsed else "h2"
    return (
        f'<{heading} id="table{spec.id}">{esc(spec.title + who)}</{heading}><p class="note">'
        f"{esc(spec.intro)} "
        "Cells: AP [95% bootstrap interval over query images]; colour: method §9's verdict "
        "against chance (see the legend)."
        f'</p><table data-table="{spec.id}"><tr><th>AP</th>{head}</tr>{"".join(rows)}</table>'
        f"{warn}"
    )


def localization_table(
    loc: pd.DataFrame, radius: float, who: str = "", anchor: str = "localization"
) -> str:
    """The localization-quality table (method §10) of ``who`` (``anchor``: its id)."""
    cols = loc_columns(loc)
    head = "".join(f"<th>{esc(lab)}</th>" for _, lab, _ in cols)

    def rows(df: pd.DataFrame) -> str:
        return "".join(
            f'<tr><td>{esc(r.proposal_method)}</td><td class="l">{esc(r.season_pair)}</td>'
            + "".join(
                f"<td>{int(getattr(r, c))}</td>"
                if d == 0
                else f"<td>{num(float(getattr(r, c)), d)}</td>"
                for c, _, d in cols
            )
            + "</tr>"
            for r in df.itertuples(index=False)
        )

    table = f"<tr><th>proposals</th><th>season pair</th>{head}</tr>"
    return (
        f'<h2 id="{anchor}">Localization quality{esc(who)}</h2><p class="note">'
        "Every change figure rests on these ranks. Ground truth: "
        f"the reference frames within {radius:g} m of the paired frame (the place). R@k: "
        "share of query subimages whose place "
        "ranks within the first k; median r: 0.5 is chance; clean: subimages of annotated "
        "frames with RoC &le; 0.05.</p>"
        f'<table data-table="{anchor}">{table}{rows(loc[loc["season_pair"] == "all"])}</table>'
        "<details><summary>per season "
        f"pair</summary><table>{table}{rows(loc[loc['season_pair'] != 'all'])}</table></details>"
    )


def heatmap(summ: pd.DataFrame, fusion_rule: str, split: str) -> str:
    """Table I's AP of one method per season pair, at ``split``."""
    d = summ[
        (summ["table"] == "I")
        & (summ["proposal_method"] == "all")
        & (summ["season_pair"] != "all")
        & (summ["fusion"] == fusion_rule)
        & (summ["split"] == split)
    ]
    if not len(d):
        return ""
    return heat_table(
        d.set_index("season_pair")["ap"].to_dict(),
        d.set_index("season_pair")["floor"].to_dict(),
        "heatmapI",
        f"{METHOD_LABELS[fusion_rule]}, Table I (the paper's protocol), {split}",
    )


def heatmap_stratified(rows: pd.DataFrame, fusion_rule: str, split: str) -> str:
    """Table S's AP of one method per season pair (query season down, reference across).

    ``rows``: the split's rows of ``splits/season_pairs_stratified.parquet``
    (:func:`harness.evaluate.breakdowns.season_pair_aps`).
    """
    d = rows[rows["fusion"] == fusion_rule] if len(rows) else rows
    if not len(d):
        return ""
    pairs = dict(zip(d["season_pair"].astype(str), d["ap"].astype(float), strict=True))
    floors = dict(zip(d["season_pair"].astype(str), d["floor"].astype(float), strict=True))
    return heat_table(
        pairs,
        floors,
        "heatmap",
        f"{METHOD_LABELS[fusion_rule]}, Table S (size-stratified), {split}",
    )


def heat_table(pairs: dict[str, float], floors: dict[str, float], anchor: str, what: str) -> str:
    """A season x season table of ``what`` per pair, coloured against each pair's floor."""
    seasons = sorted(
        {p.split("->")[0] for p in pairs} | {p.split("->")[1] for p in pairs},
        key=lambda s: ["WI", "SP", "SU", "AU"].index(s) if s in ("WI", "SP", "SU", "AU") else 9,
    )
    head = "".join(f"<th>{esc(s)}</th>" for s in seasons)

    def cell(q: str, r: str) -> str:
        if q == r:
            return '<td class="diag">&mdash;</td>'
        key = f"{q}->{r}"
        if key not in pairs:
            return '<td class="diag">no pair</td>'
        ap, fl = pairs[key], floors.get(key, NAN)
        colour = verdict_colour(ap, fl, "untested")[1]
        text = num(ap) if ap == ap else "NaN"
        return f'<td style="background:{colour}" title="floor {num(fl)}">{text}</td>'

    rows = "".join(
        f"<tr><th>{esc(q)}</th>" + "".join(cell(q, r) for r in seasons) + "</tr>" for q in seasons
    )
    return (
        f'<h3 id="{anchor}">AP per season pair</h3><p class="note">{esc(what)}; query season '
        "down, reference season across. &mdash;: a season is never paired with itself; NaN: "
        "the pair has no positive (or no stratum with both labels); no pair: no query of that "
        "season found a reference of the other. A per-pair AP has no interval (few query "
        "images per pair): its colour is the pale scale of the legend and decides nothing "
        "(hover a cell for its floor).</p>"
        f'<table data-table="{anchor}"><tr><th>query \\ reference</th>{head}</tr>{rows}</table>'
    )


def _l_cell(c: LCell) -> str:
    """One cell of Table L as HTML: an AP coloured by its verdict, a difference by its sign."""
    if c.why:
        return f'<td title="{esc(WHY[c.why])}">-<sup>{c.why}</sup></td>'
    v, lo, hi = c.value, c.low, c.high
    if c.kind == "ap":
        return (
            '<td data-verdict="{}" style="background:{}">'.format(
                *verdict_colour(v, c.floor, c.verdict)
            )
            + num(v)
            + (f' <span class="ci">[{num(lo)}, {num(hi)}]</span>' if lo == lo else "")
            + (
                f' <span class="few">{esc(few_text(c.positive_images))}</span>'
                if c.verdict == "few"
                else ""
            )
            + "</td>"
        )
    if c.kind == "diff":
        return (
            "<td></td>"
            if v != v
            else f'<td style="background:{diff_colour(lo, hi)}"'
            + (' data-holm="1"' if c.holm else "")
            + f'>{v:+.2f} <span class="ci">[{lo:+.2f}, {hi:+.2f}]</span>'
            + (" <b>[Holm]</b>" if c.holm else "")
            + "</td>"
        )
    return f"<td>{c.text()}</td>"


def table_l(out: Path, machine: str = "") -> str:
    """Table L (method §11) from ``tableL.csv``: every AP coloured against its floor.

    Then what each localizer costs; an undefined cell is ``-`` with its reason in a footnote.
    """
    v = leader_table(pd.read_csv(out / "tableL.csv"))
    head = "".join(
        f"<th>{esc(h)}</th>" for h in ("localizer", *v.heads[:-1], f"S rank fusion - {v.first}")
    )
    rows = [
        f"<tr><td>{esc(name)}</td>" + "".join(_l_cell(c) for c in cs) + "</tr>"
        for name, cs in v.rows
    ]
    rows.append(
        f'<tr class="floor"><td>floor ({esc(v.first)})</td>'
        + "<td></td>" * len(v.recall_heads)
        + "".join(f"<td>{num(f)}</td>" for f in v.floors)
        + "<td></td></tr>"
    )
    cost_rows = [
        f"<tr><td>{esc(name)}</td>" + "".join(_l_cell(c) for c in cs) + "</tr>"
        for name, cs in v.cost_rows
    ]
    cost_head = "".join(
        f"<th>{esc(h)}</th>" for h in ("localizer", *(h for _, h, _ in COST_COLUMNS))
    )
    return (
        '<h2 id="tableL">Table L: localizers</h2><p class="note">One row per localizer and '
        "one for all localizers fused by rank (method §11), every one scored on the same "
        f"query images. Table S at RoC-max {v.roc_max:.2f}; each AP with its "
        "95% interval, coloured by method §9's verdict against chance (random orders of the same "
        "samples, and the paired difference from the random baseline); "
        f"the last column is the paired difference from {esc(v.first)} in Table S rank fusion over "
        "the same bootstrap resamples ([Holm]: it survives Holm's correction over the "
        "localizers' differences). Recall: the ground-truth place ranked within the first N "
        f'({esc(", ".join(v.recall_heads))}).</p><table data-table="L"><tr>{head}</tr>'
        f"{''.join(rows)}</table>"
        + (f'<p class="warn" data-bounds="L">{esc(v.bounds_note)}</p>' if v.bounds_note else "")
        + f'<h3>What each localizer costs</h3><table data-table="L-cost"><tr>{cost_head}</tr>'
        f'{"".join(cost_rows)}</table><p class="note">{esc(COST_NOTE)}'
        + (f" Measured on: {esc(machine)}." if machine else "")
        + "</p>"
        + "".join(
            f'<p class="note"><sup>{m}</sup> -: {esc(WHY[m])}.</p>'
            for m in sorted({*v.marks, *v.cost_marks})
        )
    )


def other_blocks(summ: pd.DataFrame, names: list[str], warnings: dict[str, list[str]]) -> str:
    """Tables S and P of every localizer after the first, and of ``all localizers``."""
    parts = []
    for name in names:
        s = summ[summ["localizer"] == name]
        methods = tuple(m for m in METHOD_LABELS if m in set(s["fusion"]))
        pre = f"[{name}] "
        for t in ("S", "P"):
            notes = [w[len(pre) :] for w in warnings.get(t, []) if w.startswith(pre)]
            html = change_html(change_table(s, t, methods, notes), f" (localizer: {name})")
            parts.append(html.replace(f'id="table{t}"', f'data-localizer="{esc(name)}"', 1))
    return (
        '<h2 id="blocks">Tables S and P of the other localizers</h2>'
        "<p class='note'>The same tables, each localizer's boxes alone; <i>all localizers</i>: "
        "every localizer's boxes fused by rank (no score method is defined across "
        "localizers).</p>" + "".join(parts).replace("<h2 ", "<h3 ").replace("</h2>", "</h3>")
    )


def registered_table(spec: report_tables.TableSpec, frame: pd.DataFrame) -> str:
    """A registered table (:mod:`harness.reports.tables`) with the console's cells.

    Each AP is coloured against its own floor, each paired difference by whether its interval
    clears zero.
    """
    head = "".join(f"<th>{esc(c.header)}</th>" for c in spec.columns)
    rows = []
    for _, r in frame.iterrows():
        cells = []
        for c in spec.columns:
            text = esc(report_tables.cell(c, r))
            if c.kind == "ap":
                v, lo, hi, fl = (float(r[f]) for f in c.fields())
                word = str(r.get(f"{c.key}_verdict", "untested"))
                cells.append(
                    '<td data-verdict="{}" style="background:{}">'.format(
                        *verdict_colour(v, fl, word)
                    )
                    + text
                    + "</td>"
                )
            elif c.kind == "diff":
                _, lo, hi = (float(r[f]) for f in c.fields())
                cells.append(f'<td style="background:{diff_colour(lo, hi)}">{text}</td>')
            else:
                cells.append(f"<td>{text}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return (
        f'<h2 id="{esc(spec.stem)}">Table {esc(spec.id)}: {esc(spec.title)}</h2>'
        f'<p class="note">{esc(spec.intro)}</p>'
        f'<table data-table="{esc(spec.id)}"><tr>{head}</tr>{"".join(rows)}</table>'
    )

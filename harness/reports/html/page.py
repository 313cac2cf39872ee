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

import logging
from pathlib import Path
from typing import Any

import pandas as pd

from harness.imagestore import local_uri
from harness.ingest.annotations import load_annotations
from harness.methods import METHOD_LABELS
from harness.reports import tables as report_tables
from harness.reports.change import CHANGE_TABLES, change_table
from harness.reports.html.cells import (
    LEGEND,
    change_html,
    diff_colour,
    esc,
    heatmap,
    heatmap_stratified,
    localization_table,
    other_blocks,
    registered_table,
    table_l,
)
from harness.reports.html.gallery import gallery_html, pr_figure_html
from harness.reports.render import HOLM_MARK, holm_sentence
from harness.runtime.cache import write_text
from harness.runtime.outdirs import read_run_record

log = logging.getLogger(__name__)


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


log = logging.getLogger(__name__)


def headline_split(out: Path, headline: float) -> Path | None:
    """The split report at the headline RoC-max (else the largest one written)."""
    files = sorted((out / "splits").glob("roc_max_*.parquet"))
    want = out / "splits" / f"roc_max_{headline:.2f}.parquet"
    return want if want in files else (files[-1] if files else None)


def rank_counts_table(rank_counts: object) -> str:
    """The ranking counts of run.json as a small table.

    A row per session (per localizer and session in a run of several), a column per count:
    ``{session: {count: n}}`` or ``{localizer: {session: {count: n}}}``.
    """
    if not isinstance(rank_counts, dict) or not rank_counts:
        return "-"
    rows: list[tuple[str, dict]] = []
    for name, c in rank_counts.items():
        if isinstance(c, dict) and c and all(isinstance(v, dict) for v in c.values()):
            rows += [(f"{name} / {s}", cc) for s, cc in c.items()]  # per localizer
        elif isinstance(c, dict):
            rows.append((str(name), c))
    cols = list(dict.fromkeys(k for _, c in rows for k in c))
    head = "".join(f"<th>{esc(k.replace('_', ' '))}</th>" for k in ["session", *cols])
    body = "".join(
        f"<tr><td>{esc(who)}</td>"
        + "".join(f"<td>{esc(c.get(k, ''))}</td>" for k in cols)
        + "</tr>"
        for who, c in rows
    )
    return f'<table class="counts" data-table="rank-counts"><tr>{head}</tr>{body}</table>'


def localization_also(out: Path, cfg: dict[str, Any], lead: str, who: str) -> str:
    """The localization table at ``[report] gt_radius_also`` where the run wrote one."""
    path = out / "localization_also.csv"
    if not path.is_file():
        return ""
    loc = pd.read_csv(path)
    if lead:
        loc = loc[loc["localizer"] == lead]
    radius = float(cfg["report"].get("gt_radius_also", 0.0))
    return localization_table(loc, radius, f"{who}, place {radius:g} m", "localization-also")


def run_facts(run: dict[str, Any], cfg: dict[str, Any]) -> tuple[str, str]:
    """The localizers' names and the rows of the page's *Run* table (config, versions, counts)."""
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
    ]
    fact_rows = "".join(f"<tr><td>{esc(k)}</td><td>{esc(v)}</td></tr>" for k, v in facts)
    fact_rows += f"<tr><td>ranking</td><td>{rank_counts_table(counts.get('rank_counts'))}</td></tr>"
    return loc_name, fact_rows


def comparisons_html(summ: pd.DataFrame, methods: tuple[str, ...]) -> str:
    """The section of paired comparisons: AP(method) - AP(rank fusion), per table and split.

    Each difference with its bootstrap interval, coloured by it, and Holm's mark where it holds.
    """
    cmp_rows = summ[
        (summ["proposal_method"] == "all") & (summ["season_pair"] == "all") & summ["diff"].notna()
    ]
    cmp_html = ""
    for table in ("S", "P", "I"):  # the fair tables first, the paper's protocol last
        t = cmp_rows[cmp_rows["table"] == table]
        if not len(t):
            continue
        d = t.pivot(index="fusion", columns="split", values="diff").reindex(
            [m for m in methods if m in set(t["fusion"])]
        )
        lo = t.pivot(index="fusion", columns="split", values="diff_ci_low").reindex(d.index)
        hi = t.pivot(index="fusion", columns="split", values="diff_ci_high").reindex(d.index)
        kept = (
            t.pivot(index="fusion", columns="split", values="holm_survives")
            .reindex(d.index)
            .fillna(False)
            .astype(bool)
            if "holm_survives" in t.columns
            else d.notna() & False
        )
        cols = [c for c in t["split"].drop_duplicates()]
        head = "".join(f"<th>{esc(c)}</th>" for c in cols)
        diffs = "".join(
            f"<tr><td>{esc(METHOD_LABELS[m])} &minus; rank fusion</td>"
            + "".join(
                f'<td style="background:{diff_colour(lo.loc[m, c], hi.loc[m, c])}"'
                + (' data-holm="1"' if kept.loc[m, c] else "")
                + f">{d.loc[m, c]:+.2f} "
                f'<span class="ci">[{lo.loc[m, c]:+.2f}, {hi.loc[m, c]:+.2f}]</span>'
                + (f" <b>{esc(HOLM_MARK)}</b>" if kept.loc[m, c] else "")
                + "</td>"
                for c in cols
            )
            + "</tr>"
            for m in d.index
        )
        cmp_html += (
            f"<h3>{esc(CHANGE_TABLES[table].title)}</h3>"
            f'<p class="note">{esc(holm_sentence(t, CHANGE_TABLES[table].title))}</p><table '
            f'data-table="cmp{table}"><tr><th>difference</th>{head}</tr>{diffs}</table>'
        )
    return (
        '<h2 id="comparisons">Paired comparisons with rank fusion</h2><p '
        'class="note">AP(method) &minus; AP(rank fusion) over the same '
        "bootstrap resamples of query images, with its 95% interval; green: better than "
        "rank fusion, red: worse, white: cannot be told apart "
        "on this data.</p>" + cmp_html
    )


def protocol_section(
    summ: pd.DataFrame,
    methods: tuple[str, ...],
    lines: list[str],
    who: str,
    heat: str,
    pr_i: str,
    gallery_i: str,
) -> str:
    """The paper's protocol (Table I) at the end of the page, collapsed, with its warnings."""
    confound = [w for w in lines if w.startswith("WARNING")]
    notes_i = [w for w in lines if not w.startswith("WARNING")]
    protocol = (
        '<h2 id="protocol">The paper\'s protocol (Table I): read it last</h2>'
        "<p class='note'>Table I labels a box positive when it is at least 90% inside a change "
        "<i>and</i> at most 40% of the image, negative when it is at most RoC-max changed "
        "<i>and</i> at least 40% of the image: box size alone can separate the labels, so its "
        "APs measure box size as much as change. It is here to compare with the paper's "
        "numbers, not to compare detectors (Table S does that).</p>"
        + "".join(f'<div class="warn">{esc(w)}</div>' for w in confound)
        + "<details><summary>Table I, its PR curve, AP per season pair and worst cases "
        "under its labels</summary>"
        + change_html(change_table(summ, "I", methods, notes_i), who)
        + f'<div class="grid pr" id="prI">{pr_i}</div>'
        + heat
        + gallery_i
        + "</details>"
    )
    return protocol


def nav_html(multi: bool, extra: list[tuple[str, str]]) -> str:
    """The page's table of contents: (anchor, title) of every section, registered tables too."""
    return (
        "<nav>"
        + "".join(
            f'<a href="#{a}">{t}</a>'
            for a, t in (
                ("facts", "run"),
                ("localization", "localization"),
                *([("tableL", "Table L"), ("blocks", "per localizer")] if multi else []),
                ("tableS", "Table S"),
                ("tableP", "Table P"),
                *extra,
                ("comparisons", "comparisons"),
                ("pr", "PR curve"),
                ("heatmap", "season pairs"),
                ("gallery", "change maps"),
                ("protocol", "Table I (paper's protocol)"),
            )
        )
        + "</nav>"
    )


def page_html(title: str, body: list[str]) -> str:
    """The whole HTML document: head (title, style, script) and the sections of ``body``."""
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><meta name='viewport' "
        "content='width=device-width, initial-scale=1'>"
        f"<title>dbl-harness report: {esc(title)}</title>"
        f"<style>{CSS}</style><script>{SCRIPT}</script></head><body>"
        + "\n".join(body)
        + "</body></html>\n"
    )


def page_figures(
    out: Path,
    split_file: Path | None,
    rep: pd.DataFrame | None,
    n: int,
    data: tuple[pd.DataFrame, Any, pd.DataFrame],
    edges: list[float],
    only: str | None,
) -> tuple[str, str, str, str]:
    """PR curves (Table S and I labels) and galleries, written under ``out/report/``.

    Images of an earlier page that this one no longer shows are removed. ``data``: frames,
    annotations, ranks. Returns the HTML of the PR figure (S, I) and of the galleries (S, I).
    """
    frames, ann, ranks = data
    split_name = split_file.stem if split_file is not None else ""
    pr_s, pr_files = (
        pr_figure_html(
            out, rep, "label_stratified", "S", f"Table S labels (RoC only), {split_name}"
        )
        if rep is not None
        else ("", [])
    )
    pr_i, pr_files_i = (
        pr_figure_html(out, rep, "label", "I", f"Table I labels (the paper's), {split_name}")
        if rep is not None
        else ("", [])
    )
    gallery_s, thumbs = gallery_html(
        out, split_file, n, frames, ann, ranks, "label_stratified", edges, only
    )
    # the paper's protocol is collapsed at the end: one example per method and kind is enough there
    gallery_i, thumbs_i = gallery_html(
        out, split_file, min(n, 1), frames, ann, ranks, "label", edges, only
    )
    keep = {p.resolve() for p in [*thumbs, *thumbs_i, *pr_files, *pr_files_i]}
    for p in (out / "report").glob("*") if (out / "report").is_dir() else []:
        if p.suffix in (".jpg", ".png") and p.resolve() not in keep:
            p.unlink()  # images of an earlier page that this page no longer shows
    return pr_s, pr_i, gallery_s, gallery_i


def run_frames(out: Path, run: dict[str, Any]) -> tuple[pd.DataFrame, Any]:
    """The run's frames (image paths as this machine reads them) and its annotations."""
    cfg = run["config"]
    frames = pd.read_parquet(out / "cache" / "frames" / run["keys"]["frames"] / "frames.parquet")
    frames["image"] = [local_uri(u, out, Path(cfg["data_root"])) for u in frames["image"]]
    ann = load_annotations(Path(cfg["annotations"]))
    return frames, ann


def block_lines(warnings: dict[str, list[str]], block: str | None) -> dict[str, list[str]]:
    """The warnings and notes of one localizer's block (the record prefixes each with its name).

    ``block`` None: a run of one localizer, whose lines have no prefix.
    """
    if block is None:
        return warnings
    pre = f"[{block}] "
    return {t: [w[len(pre) :] for w in ws if w.startswith(pre)] for t, ws in warnings.items()}


def write_html_report(out: Path, gallery: int | None = None) -> Path:
    """Write ``out/report.html`` (and its images under ``out/report/``) for a finished run.

    Raises:
        HarnessError: ``out`` holds no finished run (no ``run.json``).
    """
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
    extra = report_tables.written(out)  # registered tables (harness/reports/tables.py)
    summ = summ_all[summ_all["localizer"] == lead_name] if multi else summ_all
    if multi:
        loc = loc[loc["localizer"] == lead_name]
        ranks = ranks[ranks["localizer"] == lead_name]
    methods = tuple(m for m in METHOD_LABELS if m in set(summ["fusion"]))
    warnings = block_lines(run.get("warnings", {}), lead_name if multi else None)
    loc_name, fact_rows = run_facts(run, cfg)
    who = f" (localizer: {lead_name}; data: {Path(str(cfg['data_root'])).name})"
    headline = float(cfg["report"].get("headline_roc_max", 0.05))
    split_file = headline_split(out, headline)
    split_name = split_file.stem if split_file is not None else ""
    edges = [float(e) for e in cfg["splits"]["sob_strata"]]
    (out / "report").mkdir(exist_ok=True)
    rep = pd.read_parquet(split_file) if split_file is not None else None
    if rep is not None and multi:
        rep = rep[rep["localizer"] == lead_name]
    lead = "rank_fusion" if "rank_fusion" in methods else methods[0]
    only = lead_name if multi else None
    pr_s, pr_i, gallery_s, gallery_i = page_figures(
        out, split_file, rep, n, (*run_frames(out, run), ranks), edges, only
    )
    heat_s = heatmap_stratified(rep, lead, edges, split_name) if rep is not None else ""
    protocol = protocol_section(
        summ, methods, warnings.get("I", []), who, heatmap(summ, lead, split_name), pr_i, gallery_i
    )
    body = [
        f"<h1>Detection-by-Localization: {esc(cfg['name'])}, localizer {esc(loc_name)}</h1>",
        (
            f"<p class='sub'>data: {esc(cfg['data_root'])}; dbl-harness "
            f"{esc(run['versions'].get('dbl-harness', ''))}, seed {run['seed']}</p>"
        ),
        nav_html(multi, [(spec.stem, f"Table {spec.id}") for spec, _ in extra]),
        f'<h2 id="facts">Run</h2><table class="facts" data-table="facts">{fact_rows}</table>',
        localization_table(loc, float(cfg["retrieval"]["gt_radius_m"]), who),
        localization_also(out, cfg, lead_name if multi else "", who),
        LEGEND,
        table_l(out, str(run.get("costs", {}).get("machine", ""))) if multi else "",
        other_blocks(summ_all, names[1:], run.get("warnings", {})) if multi else "",
        (
            f"<p class='note'>The sections below show localizer {esc(lead_name)}, the first of "
            f"{len(names) - 1}; the others' Tables S and P are above, every table of every "
            "localizer in tableS.md, tableP.md, table1.md.</p>"
            if multi
            else ""
        ),
        *(change_html(change_table(summ, t, methods, warnings.get(t, [])), who) for t in "SP"),
        *(registered_table(spec, frame) for spec, frame in extra),
        comparisons_html(summ, methods),
        (
            f'<h2 id="pr">Precision-recall curve (Table S labels, {esc(split_name)})</h2>'
            "<p class='note'>The six methods' curves over the samples of all size strata "
            "pooled (Table S's AP is the mean of the per-stratum APs, weighted by positives). "
            "The other RoC-max splits: <code>plots/pr_*.png</code>.</p>"
            f'<div class="grid pr">{pr_s}</div>'
        ),
        heat_s,
        gallery_s,
        protocol,
    ]
    write_text(out / "report.html", page_html(f"{cfg['name']}, localizer {loc_name}", body))
    log.info("report: wrote %s", out / "report.html")
    return out / "report.html"

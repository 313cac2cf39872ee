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
from harness.reports.change import change_table
from harness.reports.html.cells import (
    LEGEND,
    change_html,
    esc,
    heatmap,
    heatmap_stratified,
    localization_table,
    other_blocks,
    registered_table,
    table_l,
)
from harness.reports.html.gallery import gallery_html, pr_figure_html
from harness.reports.html.sections import comparisons_html, protocol_section, run_facts
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


def headline_split_file(out: Path, headline: float) -> Path | None:
    """The split report at the headline RoC-max (else the largest one written)."""
    files = sorted((out / "splits").glob("roc_max_*.parquet"))
    want = out / "splits" / f"roc_max_{headline:.2f}.parquet"
    return want if want in files else (files[-1] if files else None)


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
            out,
            written_rows(out, "pr_curves_stratified", split_name, only),
            "S",
            f"Table S labels (RoC only), {split_name}",
        )
        if rep is not None
        else ("", [])
    )
    pr_i, pr_files_i = (
        pr_figure_html(
            out,
            written_rows(out, "pr_curves", split_name, only),
            "I",
            f"Table I labels (the paper's), {split_name}",
        )
        if rep is not None
        else ("", [])
    )
    gallery_s, thumbs = gallery_html(
        out, split_file, n, (frames, ann, ranks), "label_stratified", edges, only
    )
    # the paper's protocol is collapsed at the end: one example per method and kind is enough there
    gallery_i, thumbs_i = gallery_html(
        out, split_file, min(n, 1), (frames, ann, ranks), "label", edges, only
    )
    keep = {p.resolve() for p in [*thumbs, *thumbs_i, *pr_files, *pr_files_i]}
    for p in (out / "report").glob("*") if (out / "report").is_dir() else []:
        if p.suffix in (".jpg", ".png") and p.resolve() not in keep:
            p.unlink()  # images of an earlier page that this page no longer shows
    return pr_s, pr_i, gallery_s, gallery_i


def written_rows(out: Path, stem: str, split: str, localizer: str | None) -> pd.DataFrame:
    """The rows of ``splits/<stem>.parquet`` at ``split`` (of ``localizer`` where given).

    Empty where the run wrote no such file (no positive in any split).
    """
    path = out / "splits" / f"{stem}.parquet"
    if not path.is_file():
        return pd.DataFrame(columns=["split", "fusion"])
    df = pd.read_parquet(path)
    df = df[df["split"] == split]
    if localizer is not None and "localizer" in df.columns:
        df = df[df["localizer"] == localizer]
    return df.reset_index(drop=True)


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
    split_file = headline_split_file(out, headline)
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
    pairs_s = written_rows(out, "season_pairs_stratified", split_name, only)
    heat_s = heatmap_stratified(pairs_s, lead, split_name) if rep is not None else ""
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

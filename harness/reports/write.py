"""Reports of a run (method §6, 9 and 10).

Localization quality, Table I, the per-split reports and their summary, PR curves and LoC-map
figures.

Every file is written atomically; files of an earlier run into the same directory that this run
no longer produces (a split dropped from the config, an old figure) are removed, so a directory
never mixes two runs' reports.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.config.schema import Config
from harness.errors import ConfigError
from harness.evaluate.aps import sample_groups
from harness.evaluate.leaderboard import leaderboard
from harness.evaluate.localization import localization_stats
from harness.evaluate.pixel_aps import pixel_image_rows
from harness.evaluate.split_reports import page_breakdowns, split_report
from harness.evaluate.splits import Split, paper_splits
from harness.evaluate.verdicts import confound_warnings, holm_columns
from harness.reports import tables as report_tables
from harness.reports.blocks import Block, Reports
from harness.reports.change import CHANGE_TABLES, change_table, pivot
from harness.reports.files import ReportFiles, remove_old_reports
from harness.reports.leaderboard import leaderboard_csv, leaderboard_latex, leaderboard_md
from harness.reports.plots import locmap_figures, pr_plots
from harness.reports.render import (
    change_latex,
    comparisons_markdown,
    localization_latex,
    localization_markdown,
    table_csv,
    table_markdown,
)
from harness.runtime.cache import write_parquet

#: What this module defines for callers.
__all__ = ["write_reports"]

log = logging.getLogger(__name__)


# ------------------------------------------------------------------ change tables (I, S, P)


# ------------------------------------------------------------------ all reports


def write_reports(
    cfg: Config,
    out: Path,
    blocks: Sequence[Block],
    frames: pd.DataFrame,
    ann: pd.DataFrame,
    progress: Callable[[Iterable[Any]], Iterable[Any]] = lambda it: it,
) -> Reports:
    """Write every report of a run into ``out``.

    ``blocks`` are the run's :class:`Block` (method §11: one per localizer, then ``all
    localizers`` where there are several). A localizer is named in every heading and in a
    ``localizer`` column of the split reports and the summary; a block's ``notes`` are printed
    under its change tables. With one block the files are those of a one-localizer run; with
    several, each CSV gains a ``localizer`` column, each markdown/LaTeX file a section per block,
    and Table L (``tableL.*``) is written.
    """
    blocks = list(blocks)
    files = ReportFiles(out, len(blocks) > 1)
    locs, locs_also = _write_localization(cfg, files, blocks, frames, ann)
    splits = paper_splits(cfg.splits)
    allps = [
        b.samples[b.samples["proposal_method"] == "all"].reset_index(drop=True) for b in blocks
    ]
    ids = {g: i for i, g in enumerate(sorted(set().union(*(set(sample_groups(a)) for a in allps))))}
    summaries, curves, boots = _write_splits(cfg, files, blocks, allps, ids, progress(splits))
    results = [
        _block_reports(
            cfg,
            b,
            summaries[bi] + pixel_image_rows(cfg, allps[bi], frames, ann, b.methods, ids),
            locs,
            locs_also,
        )
        for bi, b in enumerate(blocks)
    ]
    summ_all = pd.concat([r.summary for r in results], ignore_index=True)
    write_parquet(files.put(out / "splits" / "summary.parquet"), summ_all)
    allc = [
        files.tag(pd.concat(c, ignore_index=True), b.name)
        for b, c in zip(blocks, curves, strict=True)
        if c
    ]
    if allc:
        write_parquet(
            files.put(out / "splits" / "pr_curves.parquet"), pd.concat(allc, ignore_index=True)
        )
    _write_change_tables(files, results)
    table_l = _write_comparisons(cfg, files, results, boots, splits)
    _write_registered(cfg, files, results)
    if cfg.report.plots:
        _write_plots(cfg, files, curves[0], blocks[0].samples, frames, ann)
    remove_old_reports(files)
    if not files.multi:
        return results[0]
    first = results[0]
    return Reports(
        summ_all,
        pd.concat([files.tag(v, k) for k, v in locs.items()], ignore_index=True),
        first.tables,
        {
            t: [f"[{r.localizer}] {w}" for r in results for w in r.warnings[t]]
            for t in ("I", "S", "P")
        },
        first.methods,
        ", ".join(r.localizer for r in results),
        results,
        table_l,
    )


def _write_splits(
    cfg: Config,
    files: ReportFiles,
    blocks: list[Block],
    allps: list[pd.DataFrame],
    ids: dict,
    splits: Iterable[Split],
) -> tuple[
    list[list[dict]], list[list[pd.DataFrame]], list[dict[tuple[str, str, str], np.ndarray]]
]:
    """Write ``splits/<split>.parquet`` of every block, split by split.

    Returns, per block, its summary rows, PR curves and bootstrap APs (paired comparisons).
    """
    summaries: list[list[dict]] = [[] for _ in blocks]
    curves: list[list[pd.DataFrame]] = [[] for _ in blocks]
    boots: list[dict[tuple[str, str, str], np.ndarray]] = [{} for _ in blocks]
    page: list[list[tuple[pd.DataFrame, pd.DataFrame]]] = [[] for _ in blocks]
    for sp in splits:
        reps = []
        for bi, b in enumerate(blocks):
            rep, rows, cur = split_report(
                cfg, b.name, b.samples, b.methods, allps[bi], sp, ids, boots[bi]
            )
            summaries[bi] += rows
            curves[bi] += cur
            reps.append(rep)
            page[bi].append(page_breakdowns(cfg, b.methods, rep, sp.name))
        write_parquet(
            files.put(files.out / "splits" / f"{sp.name}.parquet"),
            pd.concat(reps, ignore_index=True),
        )
        del reps
    _write_breakdowns(files, blocks, page)
    return summaries, curves, boots


def _write_breakdowns(
    files: ReportFiles, blocks: list[Block], page: list[list[tuple[pd.DataFrame, pd.DataFrame]]]
) -> None:
    """``splits/pr_curves_stratified.parquet`` and ``splits/season_pairs_stratified.parquet``."""
    for k, stem in enumerate(("pr_curves_stratified", "season_pairs_stratified")):
        parts = [
            files.tag(pb[k], b.name)
            for b, pbs in zip(blocks, page, strict=True)
            for pb in pbs
            if len(pb[k])
        ]
        if parts:
            path = files.put(files.out / "splits" / f"{stem}.parquet")
            write_parquet(path, pd.concat(parts, ignore_index=True))


def _write_localization(
    cfg: Config,
    files: ReportFiles,
    blocks: list[Block],
    frames: pd.DataFrame,
    ann: pd.DataFrame,
) -> tuple[dict[str, pd.DataFrame], dict[str, pd.DataFrame]]:
    """``localization.*`` (and ``localization_also.*``) and ``ranks.parquet`` of every block.

    Returns the localization table per block name, at ``gt_radius_m`` and at ``gt_radius_also``.
    """
    located = [b for b in blocks if b.ranks is not None]
    locs = {
        b.name: localization_stats(b.ranks, frames, ann, cfg.report.recall_at)
        for b in located
        if b.ranks is not None
    }
    files.text(
        "localization.csv",
        pd.concat([files.tag(v, k) for k, v in locs.items()], ignore_index=True).to_csv(
            index=False, float_format="%.4f"
        ),
    )
    files.text(
        "localization.md",
        "\n".join(localization_markdown(v, cfg.retrieval.gt_radius_m, k) for k, v in locs.items()),
    )
    files.text("localization.tex", "\n".join(localization_latex(v, k) for k, v in locs.items()))
    also = cfg.report.gt_radius_also
    locs_also = {
        b.name: localization_stats(b.ranks_also, frames, ann, cfg.report.recall_at)
        for b in located
        if b.ranks_also is not None
    }
    if locs_also:  # the same table with the place gt_radius_also wide
        files.text(
            "localization_also.csv",
            pd.concat(
                [files.tag(v, k).assign(gt_radius_m=also) for k, v in locs_also.items()],
                ignore_index=True,
            ).to_csv(index=False, float_format="%.4f"),
        )
        files.text(
            "localization_also.md",
            "\n".join(localization_markdown(v, also, k) for k, v in locs_also.items()),
        )
        files.text(
            "localization_also.tex",
            "\n".join(localization_latex(v, k) for k, v in locs_also.items()),
        )
    write_parquet(
        files.put(files.out / "ranks.parquet"),
        pd.concat([b.ranks.assign(localizer=b.name) for b in located if b.ranks is not None]),
    )
    return locs, locs_also


def _block_reports(
    cfg: Config,
    b: Block,
    rows: list[dict],
    locs: dict[str, pd.DataFrame],
    locs_also: dict[str, pd.DataFrame],
) -> Reports:
    """One block's summary (its split, pixel and image rows, with Holm), Tables I/S/P, warnings."""
    summ = holm_columns(pd.DataFrame(rows), 1.0 - cfg.report.ci)
    summ.insert(0, "localizer", b.name)
    tables, warnings = {}, {}
    for table, spec in CHANGE_TABLES.items():
        main = summ[
            (summ["table"] == table)
            & (summ["proposal_method"] == "all")
            & (summ["season_pair"] == "all")
        ]
        warnings[table] = confound_warnings(main, spec.title) + list(b.notes)
        tables[table] = pivot(summ, table, b.methods)
    return Reports(
        summ,
        locs.get(b.name, pd.DataFrame()),
        tables,
        warnings,
        b.methods,
        b.name,
        costs=dict(b.costs),
        localization_also=locs_also.get(b.name),
    )


def _write_change_tables(files: ReportFiles, results: list[Reports]) -> None:
    """Tables I, S and P (``table1``, ``tableS``, ``tableP``) as CSV, markdown and LaTeX."""
    for table, spec in CHANGE_TABLES.items():
        views = [
            change_table(r.summary, table, r.methods, r.warnings[table], r.localizer)
            for r in results
        ]
        files.text(
            f"{spec.stem}.csv",
            "".join(
                table_csv(t.frame(), t.localizer if files.multi else None, header=i == 0)
                for i, t in enumerate(views)
            ),
        )
        files.text(f"{spec.stem}.md", "\n".join(table_markdown(t) for t in views))
        files.text(f"{spec.stem}.tex", "\n".join(change_latex(t) for t in views))


def _write_comparisons(
    cfg: Config,
    files: ReportFiles,
    results: list[Reports],
    boots: list[dict[tuple[str, str, str], np.ndarray]],
    splits: list[Split],
) -> pd.DataFrame | None:
    """``comparisons.md``, and with several localizers Table L (``tableL.*``), returned."""
    table_l = None
    cmp_md = "\n".join(comparisons_markdown(r.summary, r.methods, r.localizer) for r in results)
    if files.multi:
        table_l = leaderboard(cfg, results, boots, splits)
        files.text("tableL.csv", leaderboard_csv(table_l))
        files.text("tableL.md", leaderboard_md(table_l, cfg))
        files.text("tableL.tex", leaderboard_latex(table_l))
        cmp_md = leaderboard_md(table_l, cfg, comparisons=True) + "\n" + cmp_md
    files.text("comparisons.md", cmp_md)
    return table_l


def _write_registered(cfg: Config, files: ReportFiles, results: list[Reports]) -> None:
    """The registered tables (harness/reports/tables.py) that have rows for this run."""
    for spec in report_tables.load_builtin().values():
        try:
            frame = spec.compute(cfg, results)
            if frame is None or not len(frame):
                continue
            frame = report_tables.check_frame(spec, frame)
        except ValueError as err:
            raise ConfigError(f"report table {spec.id!r}: {err}") from err
        files.text(f"{spec.stem}.csv", report_tables.to_csv(frame))
        files.text(f"{spec.stem}.md", report_tables.to_markdown(spec, frame))
        files.text(f"{spec.stem}.tex", report_tables.to_latex(spec, frame))


def _write_plots(
    cfg: Config,
    files: ReportFiles,
    curves: list[pd.DataFrame],
    samples: pd.DataFrame,
    frames: pd.DataFrame,
    ann: pd.DataFrame,
) -> None:
    """The first block's PR curves (``plots/``) and LoC-map figures (``locmaps/``)."""
    if curves:
        for png in pr_plots(pd.concat(curves, ignore_index=True), files.out / "plots"):
            files.put(png)
    for png in locmap_figures(
        samples, frames, ann, files.out / "locmaps", cfg.report.locmap_examples
    ):
        files.put(png)

"""One block's evaluation at one split (method §8-10): split report, summary rows, breakdowns.

Its PR curves too, and the page's PR curves and AP per season pair under Table S's labels.

``harness.reports.write`` calls these for each split and block and writes what they return.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from harness.evaluate.aps import pooled_rows, stratified_labels, table_i_rows
from harness.evaluate.breakdowns import pr_curves, season_pair_aps
from harness.evaluate.config import EvalSettings
from harness.evaluate.splits import Split
from harness.evaluate.splits import label as split_label
from harness.methods import FUSION_METHODS


def split_report(
    cfg: EvalSettings,
    name: str,
    samples: pd.DataFrame,
    methods: tuple[str, ...],
    allp: pd.DataFrame,
    sp: Split,
    ids: dict[str, int],
    boots: dict[tuple[str, str, str], np.ndarray],
) -> tuple[pd.DataFrame, list[dict], list[pd.DataFrame]]:
    """One block's split report at split ``sp``, its summary rows and its PR curves.

    ``name``: the block's (its localizer's); ``samples``: its samples; ``allp``: their rows of
    every proposal together; ``ids``: the query images' group ids across blocks; ``boots``: the
    bootstrap APs of the paired comparisons, filled in.
    """
    lab = split_label(samples["RoC"].to_numpy(), samples["SoB"].to_numpy(), sp)
    rep = samples.assign(
        label=lab, label_stratified=stratified_labels(samples["RoC"].to_numpy(), sp)
    )
    rep.insert(0, "localizer", name)
    summary = pooled_rows(cfg, allp, methods, sp, "I", ids, boots)
    summary += pooled_rows(cfg, allp, methods, sp, "S", ids, boots)
    for prop, g in samples.groupby("proposal_method", sort=True):
        if prop != "all":
            summary += table_i_rows(
                g, sp, methods, "all", str(prop), cfg.report.chance_draws, cfg.seed,
                cfg.report.min_positive_images,
            )  # fmt: skip
        else:
            for pair, gp in g.groupby("season_pair", sort=True):
                summary += table_i_rows(
                    gp, sp, methods, str(pair), "all", cfg.report.chance_draws, cfg.seed,
                    cfg.report.min_positive_images,
                )  # fmt: skip
    curves = pr_curves(rep[rep["proposal_method"] == "all"], methods, "label", sp.name)
    return rep, summary, curves


def page_breakdowns(
    cfg: EvalSettings, methods: Sequence[str], rep: pd.DataFrame, split: str
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """One block's breakdowns at one split for the page: PR curves and AP per season pair.

    Both under Table S's labels; the season pairs for Table I's six methods.
    """
    allg = rep[rep["proposal_method"] == "all"]
    curves = pr_curves(allg, methods, "label_stratified", split)
    six = [m for m in methods if m in FUSION_METHODS]
    chance = (cfg.report.chance_draws, cfg.seed)
    pairs = season_pair_aps(allg, six, split, cfg.splits.sob_strata, chance)
    return (pd.concat(curves, ignore_index=True) if curves else pd.DataFrame()), pairs

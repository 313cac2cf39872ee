"""The evaluation's config: ``[splits]`` (method §8), ``[report]`` (§9) and their checks."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Protocol

from harness.checks import check_range, check_value


@dataclass(frozen=True)
class SplitsConfig:
    """``[splits]``: RoC/SoB ranges of the difficulty splits and Table S strata (method §8)."""

    # the RoC-max thresholds of Table I (the paper's 0.01-0.05)
    roc_max: tuple[float, ...] = (0.01, 0.02, 0.03, 0.04, 0.05)
    # a positive's RoC range
    pos_roc: tuple[float, float] = (0.9, 1.0)
    # a positive's SoB range
    pos_sob: tuple[float, float] = (0.0, 0.4)
    # a negative's least RoC
    neg_roc_min: float = 0.0
    # a negative's SoB range
    neg_sob: tuple[float, float] = (0.4, 1.0)
    # Table S's SoB strata edges
    sob_strata: tuple[float, ...] = (
        0.0,
        0.02,
        0.05,
        0.1,
        0.2,
        0.4,
        1.0,
    )  # Table S: SoB strata edges, [lo, hi), the last closed


@dataclass(frozen=True)
class ReportConfig:
    """``[report]``: bootstrap, plots, ``report.html`` and its gallery."""

    # bootstrap resamples behind every interval
    bootstrap: int = 1000
    # the intervals' level (and Holm's family-wise error, 1 - ci)
    ci: float = 0.95
    # method §9: random orders of the same samples behind every floor and chance band (>= 200)
    chance_draws: int = 200
    # method §9, evidence before a verdict: a figure whose positives sit in fewer query images than
    # this (or whose bootstrap cannot vary it) prints "too few positives (n)" and no verdict
    min_positive_images: int = 5
    # LoC map examples on the page
    locmap_examples: int = 4
    # write the figures
    plots: bool = True
    html: bool = True  # write report.html (the one page to look at) after the tables
    gallery: int = 3  # report.html: worst false positives and missed changes shown per method
    # the RoC-max of the page's figures (PR curves, season pairs, gallery) and of Table L
    headline_roc_max: float = 0.05
    # recall@N of the localization table and Table L, as the VPR benchmarks report it
    recall_at: tuple[int, ...] = (1, 5, 10, 20)
    # > 0: the localization table again with the place this many metres wide (ranks re-ranked
    # with [retrieval] gt_radius_m replaced; nothing else changes); 0: off
    gt_radius_also: float = 0.0


def check_splits(sp: SplitsConfig, where: str) -> None:
    """``[splits]``: RoC-max values, the ranges of the positive and negative labels, strata."""
    c = check_value
    c(
        len(sp.roc_max) > 0,
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "a non-empty list of values in [0, 1]",
    )
    c(
        all(0 <= r <= 1 for r in sp.roc_max),
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "values in [0, 1]",
    )
    c(
        len(set(sp.roc_max)) == len(sp.roc_max),
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "distinct values",
    )
    check_range(where, "[splits] pos_roc", sp.pos_roc)
    check_range(where, "[splits] pos_sob", sp.pos_sob)
    check_range(where, "[splits] neg_sob", sp.neg_sob)
    c(
        0 <= sp.neg_roc_min <= min(sp.roc_max),
        where,
        "[splits] neg_roc_min",
        sp.neg_roc_min,
        f"[0, min(roc_max) = {min(sp.roc_max)}]",
    )
    st_ = sp.sob_strata
    c(
        len(st_) >= 2
        and all(a < b for a, b in itertools.pairwise(st_))
        and st_[0] >= 0
        and st_[-1] <= 1,
        where,
        "[splits] sob_strata",
        list(st_),
        "at least two increasing edges in [0, 1]",
    )


def check_report(rp: ReportConfig, where: str) -> None:
    """``[report]``: bootstrap, interval, chance draws, the page's options."""
    c = check_value
    c(
        rp.bootstrap >= 0,
        where,
        "[report] bootstrap",
        rp.bootstrap,
        ">= 0 resamples (0: no intervals)",
    )
    c(0 < rp.ci < 1, where, "[report] ci", rp.ci, "(0, 1), e.g. 0.95")
    c(
        rp.chance_draws >= 200,
        where,
        "[report] chance_draws",
        rp.chance_draws,
        ">= 200 random orders (method §9: the floor is measured, not the positive rate)",
    )
    c(
        type(rp.min_positive_images) is int and rp.min_positive_images >= 1,
        where,
        "[report] min_positive_images",
        rp.min_positive_images,
        "an integer >= 1 (query images holding a positive before a figure earns a verdict)",
    )
    c(rp.gallery >= 0, where, "[report] gallery", rp.gallery, ">= 0 thumbnails per method and kind")
    c(
        0 <= rp.headline_roc_max <= 1,
        where,
        "[report] headline_roc_max",
        rp.headline_roc_max,
        "[0, 1] (the page falls back to the largest RoC-max written)",
    )
    c(rp.locmap_examples >= 0, where, "[report] locmap_examples", rp.locmap_examples, ">= 0")


def check_recall_at(rp: ReportConfig, where: str) -> None:
    """``[report] recall_at``: increasing list positions."""
    check_value(
        len(rp.recall_at) > 0
        and all(n >= 1 for n in rp.recall_at)
        and list(rp.recall_at) == sorted(set(rp.recall_at)),
        where,
        "[report] recall_at",
        list(rp.recall_at),
        "a non-empty increasing list of list positions >= 1, e.g. [1, 5, 10, 20]",
    )


class EvalSettings(Protocol):
    """What the evaluation reads of a run's config (the root config is one)."""

    @property
    def seed(self) -> int:
        """The run's seed."""

    @property
    def splits(self) -> SplitsConfig:
        """``[splits]``."""

    @property
    def report(self) -> ReportConfig:
        """``[report]``."""

"""Bench case ``fixture-figures``: the figures README and ``docs/`` quote from fixture variants.

The fixture run of ``datasets/fixture.toml`` (what ``make reproduce-table`` prints; its autoencoder
trained afresh, not copied from the kept ``datasets/models``, so that its training time is the
budget's), then the same run with one setting changed, each in a directory of its own that starts
from the default run's cache (so only what the setting changes runs again):

- ``[descriptor] train_samples = 0`` (6 epochs over the training crops instead of the fixture's
  budget of 6,000 sample-steps),
- ``[projection] dim`` = 256, 128, 64, 32 and 64 with whitening,
- ``[retrieval] db_stride_m = 9`` with ``gt_radius_m = 5``,
- ``[descriptor] precision = "bf16"`` (what bf16 costs in R@1 and AP).

One row per variant: ``median`` is its R@1, ``figures`` every figure the text quotes (R@1 over all
and clean subimages, median r, Table I at RoC-max 0.03 and 0.05, Table S at 0.05, query
subimages, places lost, the wall time of the run). ``tests/test_doc_figures.py`` fails when the
README or ``docs/decisions.md`` quotes a figure these rows do not hold; it also checks the default
row against the suite's own fixture run, so the record cannot drift from the code unseen.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from .common import ROOT, emit

VARIANTS: dict[str, dict[str, dict[str, Any]]] = {
    "default": {"descriptor": {"trained_models": ""}},  # trained here: its time is measured
    "epochs=6": {"descriptor": {"train_samples": 0}},
    "dim=256": {"projection": {"dim": 256}},
    "dim=128": {"projection": {"dim": 128}},
    "dim=64": {"projection": {"dim": 64}},
    "dim=32": {"projection": {"dim": 32}},
    "dim=64 whiten": {"projection": {"dim": 64, "whiten": True}},
    "db_stride_m=9": {"retrieval": {"db_stride_m": 9.0, "gt_radius_m": 5.0}},
    # the encoder trained and run in bf16 (emulated where the CPU has no bf16 product)
    "precision=bf16": {"descriptor": {"precision": "bf16"}},
}
#: The figures each variant's row compares with the default run's (``vs_default``).
COMPARED = ("recall_at_1", "clean_recall_at_1", "t1_rank_fusion_005", "ts_rank_fusion_005")


def run_tables(out: Path) -> tuple[Any, Any, Any, Any]:
    """A finished run's pooled localization row, Table I, summary and Table S at RoC-max 0.05.

    Table I and Table S (the summary's rows at RoC-max 0.05) are indexed by method.
    """
    import pandas as pd

    loc = pd.read_csv(out / "localization.csv")
    row = loc[(loc["proposal_method"] == "all") & (loc["season_pair"] == "all")].iloc[0]
    t1 = pd.read_csv(out / "table1.csv").set_index("fusion")
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    ts = summ[(summ["table"] == "S") & (summ["roc_max"].round(6) == 0.05)].set_index("fusion")
    return row, t1, summ, ts


def figures(out: Path) -> dict[str, float]:
    """The quoted figures of one finished run directory, at full precision."""
    row, t1, summ, ts = run_tables(out)
    run = json.loads((out / "run.json").read_text())
    rf = ts.loc["rank_fusion"]
    return {
        "recall_at_1": float(row["recall_at_1"]),
        "clean_recall_at_1": float(row["clean_recall_at_1"]),
        "median_r": float(row["median_r"]),
        "subimages": int(row["subimages"]),
        "t1_rank_fusion_003": float(t1.loc["rank_fusion", "0.03"]),
        "t1_rank_no_fusion_003": float(t1.loc["rank_no_fusion", "0.03"]),
        "t1_rank_fusion_005": float(t1.loc["rank_fusion", "0.05"]),
        "t1_rank_no_fusion_005": float(t1.loc["rank_no_fusion", "0.05"]),
        "t1_score_max_005": float(t1.loc["score_max", "0.05"]),
        "t1_rank_fusion_asc_005": float(t1.loc["rank_fusion_asc", "0.05"]),
        "t1_cover_count_005": float(t1.loc["cover_count", "0.05"]),
        "t1_size_prior_005": float(t1.loc["size_prior", "0.05"]),
        "t1_positive_rate_005": float(
            summ[(summ["table"] == "I") & (summ["roc_max"].round(6) == 0.05)]["positive_rate"].iloc[
                0
            ]
        ),
        "ts_rank_fusion_005": float(ts.loc["rank_fusion", "ap"]),
        "ts_score_max_005": float(ts.loc["score_max", "ap"]),
        "ts_rank_fusion_ci_low_005": float(rf["ci_low"]),
        "ts_rank_fusion_ci_high_005": float(rf["ci_high"]),
        "ts_rank_fusion_vs_random_ci_low_005": float(rf["vs_random_diff_ci_low"]),
        "ts_random_005": float(ts.loc["random", "ap"]),
        "ts_floor_005": float(rf["floor"]),
        "ts_chance_low_005": float(rf["chance_low"]),
        "ts_chance_high_005": float(rf["chance_high"]),
        "ts_positive_rate_005": float(rf["positive_rate"]),
        "places_lost": _lost(run.get("counts", {})),
        "frames_not_described_min": min(run["counts"]["frames_not_described"].values()),
        "frames_not_described_max": max(run["counts"]["frames_not_described"].values()),
        "train_s": float(run["timings_s"].get("model", 0.0)),
        **_model_info(out, run),
        **measured_share(run["counts"].get("rank_counts", {})),
    }


def measured_share(counts: Any) -> dict[str, float]:
    """A bf16 ranking's share of (query, frame) comparisons measured exactly (else nothing)."""

    def total(c: Any, name: str) -> int:
        if isinstance(c, dict):
            return sum(
                int(v) if k == name and isinstance(v, int) else total(v, name) for k, v in c.items()
            )
        return 0

    compared = total(counts, "compared")
    if not compared:
        return {}
    return {"rank_measured_exactly_share": total(counts, "measured_exactly") / compared}


def _model_info(out: Path, run: dict) -> dict[str, Any]:
    """The trained model's steps and whether it stopped early (its cache entry's manifest)."""
    (key,) = run["cache_entries"]["model"]
    info = json.loads((out / "cache" / "model" / key / "manifest.json").read_text())["info"]
    return {  # an epoch-trained model records neither: its steps are epochs x batches
        "train_steps": int(info.get("steps", -1)),
        "stopped_early": bool(info.get("stopped_early", False)),
    }


def _lost(counts: Any) -> int:
    """``no_rank_place_not_in_database`` summed over every localizer and session of run.json."""
    if isinstance(counts, dict):
        return sum(
            int(v) if k == "no_rank_place_not_in_database" else _lost(v)
            for k, v in counts.items()
            if isinstance(v, dict | int) and not isinstance(v, bool)
        )
    return 0


def run_variant(base: Path, default_out: Path | None, name: str) -> tuple[Path, float]:
    """Run one variant into ``base/<name>`` (from the default run's cache); (out, wall s)."""
    from harness.config.assemble import load_config
    from harness.pipeline.chain import Pipeline

    cfg = load_config(ROOT / "datasets" / "fixture.toml")
    for section, values in VARIANTS[name].items():
        cfg = dataclasses.replace(
            cfg, **{section: dataclasses.replace(getattr(cfg, section), **values)}
        )
    out = base / name.replace(" ", "_").replace("=", "-")
    if default_out is not None:
        shutil.copytree(default_out / "cache", out / "cache")
        shutil.copy(default_out / ".dbl-harness.json", out / ".dbl-harness.json")
    t0 = time.perf_counter()
    Pipeline(cfg, out).run()
    return out, time.perf_counter() - t0


def case_fixture_figures(quick: bool) -> None:
    """Each variant's figures (``--quick``: the default run and one projection)."""
    names = ["default", "dim=64"] if quick else list(VARIANTS)
    with tempfile.TemporaryDirectory(prefix="fixture-figures-") as tmp:
        base = Path(tmp)
        default_out: Path | None = None
        default_fig: dict[str, float] = {}
        for name in names:
            out, wall = run_variant(base, default_out, name)
            fig = figures(out)
            if name == "default":
                default_out, default_fig = out, fig
            vs = {k: round(fig[k] - default_fig[k], 4) for k in COMPARED} if default_fig else {}
            emit(
                f"fixture figures [{name}]",
                [fig["recall_at_1"]],
                "R@1",
                figures=fig,
                vs_default=vs,
                wall_s=round(wall, 1),
                notes=f"datasets/fixture.toml{'' if name == 'default' else ' with ' + name}"
                + (
                    ""
                    if name == "default"
                    else "; minus the default run: "
                    + ", ".join(f"{k} {v:+.4f}" for k, v in vs.items())
                ),
            )

"""Table L's figures (method §11), computed from the blocks' summaries; the reports render them.

Each localizer's recall, its APs with intervals and floors, and its paired difference from the
first localizer.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from harness.evaluate.config import EvalSettings
from harness.evaluate.metrics import holm, paired_difference
from harness.evaluate.splits import Split
from harness.runtime.costs import COST_COLUMNS

#: (column prefix, table, split selector, method, heading) of Table L's AP columns.
AP_COLUMNS = (
    ("S_rank_fusion", "S", "headline", "rank_fusion", "Table S rank fusion"),
    ("S_score_max", "S", "headline", "score_max", "Table S score max"),
    ("P_pixel", "P", "pixel", "rank_fusion", "pixel AP (rank fusion)"),
    ("P_image", "P", "image", "rank_fusion", "image AP (rank fusion)"),
)


def headline_split(splits: Sequence[Split], roc_max: float) -> Split:
    """The split whose RoC-max is nearest the headline's (the first of equals)."""
    return min(splits, key=lambda s: abs(s.roc_max - roc_max))


def _cell(summ: pd.DataFrame, table: str, split: str, fusion_rule: str) -> dict[str, Any]:
    r = summ[
        (summ["table"] == table)
        & (summ["split"] == split)
        & (summ["fusion"] == fusion_rule)
        & (summ["proposal_method"] == "all")
        & (summ["season_pair"] == "all")
    ]
    if not len(r):
        nan = float("nan")
        return {
            **dict.fromkeys(("ap", "ci_low", "ci_high", "floor", "chance_high"), nan),
            "verdict": "undefined",
            "query_images": 0,
            "positive_images": 0,
        }
    x = r.iloc[0]
    return {
        **{k: float(x[k]) for k in ("ap", "ci_low", "ci_high", "floor", "chance_high")},
        "verdict": str(x["verdict"]),
        "query_images": int(x["query_images"]),
        "positive_images": int(x.get("positive_images", 0)),
    }


def _bound_share(la: pd.DataFrame) -> float:
    """The share of a block's ranks that are bounds (0 for a table written before the column)."""
    if not len(la) or "bound_share" not in la.columns:
        return 0.0
    return float(la["bound_share"].iloc[0])


def leaderboard(
    cfg: EvalSettings,
    blocks: Sequence[Any],
    boots: Sequence[dict[tuple[str, str, str], np.ndarray]],
    splits: Sequence[Split],
) -> pd.DataFrame:
    """Table L: one row per block (localizers first, ``all localizers`` last).

    ``blocks`` are the blocks' :class:`harness.reports.blocks.Reports` (``summary``,
    ``localization``, ``localizer``).

    ``boots[i]`` holds block i's bootstrap APs by (table, split, method); the difference of each
    row from the first is paired over the same resamples (the blocks share the query images).
    """
    head = headline_split(splits, cfg.report.headline_roc_max)
    first = boots[0].get(("S", head.name, "rank_fusion"), np.zeros(0))
    rows: list[dict[str, Any]] = []
    for b, bt in zip(blocks, boots, strict=True):
        loc = b.localization
        la = (
            loc[(loc["proposal_method"] == "all") & (loc["season_pair"] == "all")]
            if len(loc)
            else loc
        )
        row: dict[str, Any] = {
            "localizer": b.localizer,
            "roc_max": head.roc_max,
            **{
                f"recall_at_{n}": float(la[f"recall_at_{n}"].iloc[0]) if len(la) else float("nan")
                for n in cfg.report.recall_at
            },
            "subimages": int(la["subimages"].iloc[0]) if len(la) else 0,
            "bound_share": _bound_share(la),
        }
        for prefix, table, split, method, _ in AP_COLUMNS:
            c = _cell(b.summary, table, head.name if split == "headline" else split, method)
            for k in ("ap", "ci_low", "ci_high", "floor", "chance_high", "verdict"):
                row[f"{prefix}_{k}"] = c[k]
            row[f"{prefix}_positive_images"] = c["positive_images"]
            if prefix == "S_rank_fusion":
                row["query_images"] = c["query_images"]
        mine = bt.get(("S", head.name, "rank_fusion"), np.zeros(0))
        if rows and len(mine) and len(first) == len(mine):
            d = paired_difference(
                mine, first, row["S_rank_fusion_ap"], rows[0]["S_rank_fusion_ap"], cfg.report.ci
            )
        else:
            nan = float("nan")
            d = dict.fromkeys(
                ("diff", "diff_ci_low", "diff_ci_high", "sign_flip_share", "p_value"), nan
            )
        row.update({f"S_rank_fusion_{k}": v for k, v in d.items()})
        nan = float("nan")
        row.update({c: float(b.costs.get(c, nan)) for c, *_ in COST_COLUMNS})
        row["imported"] = bool(b.costs.get("imported", 0.0))
        rows.append(row)
    t = pd.DataFrame(rows)
    # the localizers' differences from the first are one family for Holm's correction
    t["S_rank_fusion_holm_survives"] = holm(
        t["S_rank_fusion_p_value"].to_numpy(np.float64), 1.0 - cfg.report.ci
    )
    return t

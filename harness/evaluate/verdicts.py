"""What the change tables say of their figures (method §7 and 9).

The confound warning where a baseline that reads no pixel nears the best method, and Holm's
correction of the paired tests.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from harness.evaluate.metrics import holm
from harness.methods import BASELINES, FUSION_METHODS

#: A baseline within this of the best of the six methods is reported under the table (method §7).
WARN_MARGIN = 0.02


def confound_warnings(main: pd.DataFrame, table: str) -> list[str]:
    """Method §7: warn where a baseline that reads no pixel nears the best method.

    Where one comes within 0.02 of the best of the six methods, say so: one line per baseline,
    naming every split where it happens and both APs.
    """
    hits: dict[str, list[str]] = {}
    for split, g in main.groupby("split", sort=False):
        six = g[g["fusion"].isin(FUSION_METHODS)].dropna(subset=["ap"])
        if not len(six):
            continue
        best = six.loc[six["ap"].idxmax()]
        for b in BASELINES:
            row = g[g["fusion"] == b]
            if (
                len(row)
                and np.isfinite(row["ap"].iloc[0])
                and row["ap"].iloc[0] >= best["ap"] - WARN_MARGIN
            ):
                name = (
                    f"RoC-max {row['roc_max'].iloc[0]:.2f}" if table != "Table P" else f"{split} AP"
                )
                hits.setdefault(b, []).append(
                    f"{name}: {row['ap'].iloc[0]:.2f} vs {best['fusion']} {best['ap']:.2f}"
                )
    see = (
        "; read Table S (tableS.md), which compares boxes of the same size"
        if table == "Table I"
        else ""
    )
    return [
        f"WARNING ({table}): the baseline {b}, which reads no pixel, comes within "
        f"{WARN_MARGIN} of the best of the six methods "
        f"({'; '.join(v)}): under this protocol it separates the labels without detecting "
        f"anything{see}."
        for b, v in hits.items()
    ]


def holm_columns(summ: pd.DataFrame, alpha: float) -> pd.DataFrame:
    """Mark the paired differences from rank fusion that survive Holm's correction.

    The family is one table's differences (every method but rank fusion, every pooled column:
    proposals ``all``, season pair ``all``), ``holm_tested`` of them; ``holm_survives`` marks those
    rejected at ``alpha`` (``1 - [report] ci``). Rows outside a family are never marked.
    """
    out = summ.copy()
    out["holm_tested"] = 0
    out["holm_survives"] = False
    if not len(out) or "p_value" not in out.columns:
        return out
    for _, g in out.groupby("table", sort=False):
        fam = g[
            (g["proposal_method"] == "all")
            & (g["season_pair"] == "all")
            & (g["fusion"] != "rank_fusion")
            & np.isfinite(g["p_value"].to_numpy(np.float64))
        ]
        out.loc[fam.index, "holm_tested"] = len(fam)
        out.loc[fam.index, "holm_survives"] = holm(fam["p_value"].to_numpy(np.float64), alpha)
    return out

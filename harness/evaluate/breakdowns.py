"""The breakdowns the report page draws, computed when the reports are written (method §8-9).

PR curves under Table I's labels and under Table S's, and Table S's AP per season pair with its
floor: the page reads them from ``splits/`` and computes nothing.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from harness.evaluate.chance import stratified_chance
from harness.evaluate.metrics import pr_curve, stratified_ap


def pr_curves(
    allg: pd.DataFrame, methods: Sequence[str], label: str, split: str
) -> list[pd.DataFrame]:
    """Each method's PR curve on ``allg`` (a split report's rows of all proposals) under ``label``.

    ``label`` is ``label`` (Table I's) or ``label_stratified`` (Table S's); a method whose
    labelled samples hold no positive has no curve. Columns: ``split``, ``fusion``,
    ``threshold``, ``precision``, ``recall``.
    """
    out = []
    for m in methods:
        sel = (allg[label] >= 0) & allg[f"loc_{m}"].notna()
        if (allg.loc[sel, label] == 1).any():
            thr, p, r = pr_curve(
                allg.loc[sel, label].to_numpy() == 1, allg.loc[sel, f"loc_{m}"].to_numpy()
            )
            out.append(
                pd.DataFrame(
                    {"split": split, "fusion": m, "threshold": thr, "precision": p, "recall": r}
                )
            )
    return out


def season_pair_aps(
    allg: pd.DataFrame,
    methods: Sequence[str],
    split: str,
    edges: Sequence[float],
    chance: tuple[int, int],
) -> pd.DataFrame:
    """Table S's AP of each method per season pair, with its floor (no interval: few images).

    ``allg``: a split report's rows of all proposals; ``edges``: the size strata; ``chance``: the
    random draws of the floor and their seed. Columns: ``split``, ``fusion``, ``season_pair``,
    ``ap``, ``floor``.
    """
    draws, seed = chance
    lab = allg[allg["label_stratified"] >= 0]
    rows = []
    for m in methods:
        col = f"loc_{m}"
        for pair, g in lab.groupby("season_pair", sort=True):
            g = g[g[col].notna()]
            y, sob = g["label_stratified"].to_numpy() == 1, g["SoB"].to_numpy()
            rows.append(
                {
                    "split": split,
                    "fusion": m,
                    "season_pair": str(pair),
                    "ap": stratified_ap(y, g[col].to_numpy(), sob, list(edges))[0],
                    "floor": stratified_chance(y, sob, np.asarray(edges), draws, seed)[0],
                }
            )
    return pd.DataFrame(rows, columns=["split", "fusion", "season_pair", "ap", "floor"])

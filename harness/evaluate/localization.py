"""The localization table's figures (method §6): Recall@N and median r.

Per proposal method and season pair, over every ranked subimage and over the clean ones, beside
their chance levels.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from harness.evaluate.splits import roc_sob
from harness.ingest.annotations import change_boxes
from harness.records import QUERY_KEY, frame_sizes

#: A query subimage is "clean" for the localization table when at most this share of it changed.
CLEAN_ROC = 0.05


def localization_stats(
    ranks: pd.DataFrame,
    frames: pd.DataFrame,
    ann: pd.DataFrame,
    recall_at: Sequence[int] = (1, 5, 10, 20),
) -> pd.DataFrame:
    """Recall@N (``[report] recall_at``) and median r per proposal method x season pair.

    Also over all pairs and all proposal methods (``all``).

    Each statistic is given over all ranked query subimages and over the clean ones (annotated
    query frames, RoC <= 0.05), next to its chance level: the mean of 1/L (recall@1 of a random
    ranking) and 0.5 (its median r).
    """
    cb = change_boxes(ann)
    size = frame_sizes(frames)
    roc = np.full(len(ranks), np.nan)
    for key, idx in ranks.groupby(QUERY_KEY, sort=False).indices.items():
        k = (str(key[0]), str(key[1]), int(key[2]))
        if k in cb:
            w, h = size[k]
            roc[idx] = roc_sob(
                ranks[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)[idx], cb[k], w, h
            )[0]
    df = ranks.assign(_clean=roc <= CLEAN_ROC)
    rows = []
    for prop, gp in [("all", df), *df.groupby("proposal_method", sort=True)]:
        for pair, g in [("all", gp), *gp.groupby("season_pair", sort=True)]:
            c = g[g["_clean"]]
            rows.append(
                {
                    "proposal_method": str(prop),
                    "season_pair": str(pair),
                    "subimages": len(g),
                    **{f"recall_at_{n}": float((g["rank"] <= n).mean()) for n in recall_at},
                    "median_r": float(g["r"].median()),
                    "chance_recall_at_1": float((1.0 / g["L"]).mean()),
                    "clean_subimages": len(c),
                    **{
                        f"clean_recall_at_{n}": float((c["rank"] <= n).mean())
                        if len(c)
                        else float("nan")
                        for n in recall_at
                    },
                    "clean_median_r": float(c["r"].median()) if len(c) else float("nan"),
                    "median_place_size": float(g["place_size"].median())
                    if "place_size" in g.columns
                    else 1.0,
                    # ranks that are only bounds: a truncated imported list without the place
                    "bound_share": float((~g["exact"].astype(bool)).mean())
                    if "exact" in g.columns and len(g)
                    else 0.0,
                }
            )
    return pd.DataFrame(rows)

"""Bring your own localizer: turn external ranked lists into the harness's rank table.

Input schema (parquet or CSV), one row per query subimage:

| column | type | meaning |
|---|---|---|
| ``q_session, q_camera, q_utime`` | str, str, int | the query frame |
| ``method`` | str | the proposal method of the subimage |
| ``box_id`` | int | the subimage's id within the frame and method |
| ``x1, y1, x2, y2`` | float | the subimage box in upright pixels |
| ``r_session`` | str | the reference session searched |
| ``ranked`` | list of int (parquet) or space-separated ints (CSV) | reference frame utimes, best first; may be truncated |
| ``L`` | int | the length of the full ranked list (frames in the database) |
| ``distance`` | float, optional | relevance score for the score-fusion baselines (larger = less similar) |

The ground-truth reference of each query frame comes from the pair table. When it is missing
from a truncated list, ``missing`` decides: ``last`` gives rank L (most changed), ``next``
gives ``len(ranked) + 1`` (a lower bound).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from .errors import RetrievalError

REQUIRED = ["q_session", "q_camera", "q_utime", "method", "box_id", "x1", "y1", "x2", "y2", "r_session", "ranked", "L"]


def read_import(path: Path) -> pd.DataFrame:
    path = Path(path)
    if not path.exists():
        raise RetrievalError(f"{path}: rank file not found")
    if path.suffix == ".parquet":
        df = pd.read_parquet(path)
    else:
        df = pd.read_csv(path, dtype={"q_session": str, "q_camera": str, "r_session": str, "method": str})
        df["ranked"] = [[int(v) for v in str(s).split()] if isinstance(s, str) else [] for s in df.get("ranked", pd.Series(dtype=str))]
    miss = [c for c in REQUIRED if c not in df.columns]
    if miss:
        raise RetrievalError(f"{path}: missing column(s) {miss}; required: {REQUIRED} (+ optional distance)")
    return df.reset_index(drop=True)


def ranks_from_import(df: pd.DataFrame, pairs: pd.DataFrame, where: str, missing: str = "last") -> tuple[pd.DataFrame, dict]:
    """Validate external ranked lists against the pairs and compute rank, L, r, d."""
    if missing not in ("last", "next"):
        raise RetrievalError(f"missing must be 'last' or 'next', got {missing!r}")
    keys = ["q_session", "q_camera", "q_utime", "r_session"]
    m = df.merge(pairs[keys + ["r_camera", "r_utime", "season_pair"]], on=keys, how="left")
    unpaired = m["r_utime"].isna().to_numpy()
    counts = {"rows": len(df), "no_pair": int(unpaired.sum()), "gt_missing_from_truncated_list": 0}
    m = m[~unpaired].reset_index(drop=True)
    rank = np.empty(len(m), np.int64)
    exact = np.ones(len(m), bool)
    for i, (lst, L, g) in enumerate(zip(m["ranked"], m["L"], m["r_utime"], strict=True)):
        lst = list(lst)
        if int(L) < len(lst) or int(L) < 1:
            raise RetrievalError(f"{where}: row {i + 1}: L = {L} is smaller than the list's length {len(lst)}")
        if len(set(lst)) != len(lst):
            raise RetrievalError(f"{where}: row {i + 1}: ranked list repeats a frame")
        g = int(g)
        if g in lst:
            rank[i] = lst.index(g) + 1
        elif len(lst) >= int(L):
            raise RetrievalError(f"{where}: row {i + 1}: the ground-truth frame {g} is missing from a complete list (L = {L})")
        else:
            counts["gt_missing_from_truncated_list"] += 1
            rank[i] = int(L) if missing == "last" else len(lst) + 1
            exact[i] = False
    out = m.drop(columns=["ranked"]).copy()
    out["rank"] = rank
    out["L"] = out["L"].astype(np.int64)
    out["r"] = rank / out["L"].to_numpy()
    out["d"] = out["distance"].astype(float) if "distance" in out.columns else np.nan
    out["exact"] = exact
    return out, counts

"""Bring your own localizer: turn external ranked lists into the harness's rank table.

Input schema (parquet or CSV), one row per query subimage:

| column | type | meaning |
|---|---|---|
| ``q_session, q_camera, q_utime`` | str, str, int | the query frame |
| ``method`` | str | the proposal method of the subimage |
| ``box_id`` | int | the subimage's id within the frame and method |
| ``x1, y1, x2, y2`` | float | the subimage box in upright pixels |
| ``r_session`` | str | the reference session searched |
| ``ranked`` | list of int (parquet) or space-separated ints (CSV) | reference frame utimes, best
first; may be truncated |
| ``L`` | int | the length of the full ranked list (frames in the database) |
| ``distance`` | float, optional | relevance score for the score-fusion baselines (larger = less
similar) |

The ground-truth reference G of each query frame comes from the pair table, and the list is
scored against G's ground-truth *place* P(G) exactly as the built-in engines are (SPEC section
6): ``rank = 1 +`` the number of listed frames outside P(G) before the first frame of P(G);
``L = 1 + (L_list - |P(G)|)``, where ``|P(G)|`` counts the place's frames in the reference
session's frame table. When no frame of P(G) appears in a truncated list, ``missing`` decides:
``last`` gives rank L (the most changed), ``next`` gives one past the listed frames outside
P(G) (a lower bound); either way the row is flagged ``exact = False`` and counted.

Reference ids are checked against the reference session's frames: when most ids match no frame
(microseconds given as nanoseconds, another session's ids) the import is refused; a few
unmatched ids are counted (``unmatched_reference_ids``) and logged.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from .cache import write_parquet
from .errors import RetrievalError

log = logging.getLogger(__name__)

#: Share of listed reference ids that must match a frame of the reference session.
MIN_MATCHED_SHARE = 0.5

REQUIRED = [
    "q_session",
    "q_camera",
    "q_utime",
    "method",
    "box_id",
    "x1",
    "y1",
    "x2",
    "y2",
    "r_session",
    "ranked",
    "L",
]


def read_import(path: Path) -> pd.DataFrame:
    """A rank file (CSV or parquet) as a table, its columns checked.

    Raises:
        RetrievalError: The file is missing, unreadable or lacks a column.
    """
    path = Path(path)
    if not path.exists():
        raise RetrievalError(f"{path}: rank file not found")
    if path.suffix == ".parquet":
        df = pd.read_parquet(path)
    else:
        df = pd.read_csv(
            path, dtype={"q_session": str, "q_camera": str, "r_session": str, "method": str}
        )
        df["ranked"] = [
            [int(v) for v in str(s).split()] if isinstance(s, str) else []
            for s in df.get("ranked", pd.Series(dtype=str))
        ]
    miss = [c for c in REQUIRED if c not in df.columns]
    if miss:
        raise RetrievalError(
            f"{path}: missing column(s) {miss}; required: {REQUIRED} (+ optional distance)"
        )
    return df.reset_index(drop=True)


def ranks_from_import(
    df: pd.DataFrame,
    pairs: pd.DataFrame,
    where: str,
    frames: pd.DataFrame | None = None,
    gt_radius_m: float = 0.0,
    max_yaw_deg: float = 45.0,
    missing: str = "last",
) -> tuple[pd.DataFrame, dict]:
    """Validate external ranked lists against the pairs and frames; compute rank, L, r, r', d.

    Args:
        df: the imported table (see the module docstring).
        pairs: the pair table (ground-truth reference frame per query frame and session).
        where: the file's name, for errors.
        frames: the frame table; with it, reference ids are checked and places are built.
        gt_radius_m: the place's radius, metres (SPEC section 6); 0 scores the frame G alone.
        max_yaw_deg: the place's heading limit, degrees.
        missing: ``last`` or ``next``, for truncated lists without the place.

    Raises:
        RetrievalError: bad lists, or reference ids that mostly match no frame.
    """
    from .pairs import ground_truth_places

    if missing not in ("last", "next"):
        raise RetrievalError(f"missing must be 'last' or 'next', got {missing!r}")
    keys = ["q_session", "q_camera", "q_utime", "r_session"]
    m = df.merge(pairs[keys + ["r_camera", "r_utime", "season_pair"]], on=keys, how="left")
    unpaired = m["r_utime"].isna().to_numpy()
    counts = {
        "rows": len(df),
        "no_pair": int(unpaired.sum()),
        "gt_missing_from_truncated_list": 0,
        "unmatched_reference_ids": 0,
    }
    m = m[~unpaired].reset_index(drop=True)
    known: dict[str, set[int]] = {}
    places: dict[tuple[str, str], dict[int, np.ndarray]] = {}
    if frames is not None:
        for (s, c), g in frames.groupby(["session", "camera"], sort=True):
            known.setdefault(str(s), set()).update(int(u) for u in g["utime"])
            gts = (
                m.loc[(m["r_session"] == s) & (m["r_camera"] == c), "r_utime"]
                .astype(np.int64)
                .to_numpy()
            )
            places[(str(s), str(c))] = ground_truth_places(g, gts, gt_radius_m, max_yaw_deg)
        listed = unmatched = 0
        example = None
        for lst, rs in zip(m["ranked"], m["r_session"], strict=True):
            ids = known.get(str(rs), set())
            for v in lst:
                listed += 1
                if int(v) not in ids:
                    unmatched += 1
                    example = example or (rs, int(v))
        counts["unmatched_reference_ids"] = unmatched
        if listed and unmatched > (1 - MIN_MATCHED_SHARE) * listed:
            raise RetrievalError(
                f"{where}: {unmatched} of {listed} listed reference ids match no frame of "
                "their reference session "
                f"(e.g. {example[1]} in session {example[0]}; frame ids are utimes in microseconds)"  # type: ignore[index]
            )
        if unmatched:
            log.warning(
                "%s: %d of %d listed reference ids match no frame of their session (e.g. "
                "%s); they count as frames outside the place",
                where,
                unmatched,
                listed,
                example,
            )
    n = len(m)
    rank = np.empty(n, np.int64)
    Lq = np.empty(n, np.int64)
    psize = np.empty(n, np.int64)
    exact = np.ones(n, bool)
    for i, (lst, L, g, rs, rc) in enumerate(
        zip(m["ranked"], m["L"], m["r_utime"], m["r_session"], m["r_camera"], strict=True)
    ):
        lst = [int(v) for v in lst]
        if int(L) < len(lst) or int(L) < 1:
            raise RetrievalError(
                f"{where}: row {i + 1}: L = {L} is smaller than the list's length {len(lst)}"
            )
        if len(set(lst)) != len(lst):
            raise RetrievalError(f"{where}: row {i + 1}: ranked list repeats a frame")
        g = int(g)
        place = places.get((str(rs), str(rc)), {}).get(g, np.array([g]))
        members = set(place.tolist())
        psize[i] = len(members)
        Lq[i] = max(1, int(L) - len(members) + 1)
        first = next((k for k, v in enumerate(lst) if v in members), None)
        if first is not None:
            rank[i] = 1 + sum(1 for v in lst[:first] if v not in members)
        elif len(lst) >= int(L):
            raise RetrievalError(
                f"{where}: row {i + 1}: the ground-truth frame {g} is missing from a "
                f"complete list (L = {L})"
            )
        else:
            counts["gt_missing_from_truncated_list"] += 1
            rank[i] = (
                Lq[i]
                if missing == "last"
                else min(Lq[i], 1 + sum(1 for v in lst if v not in members))
            )
            exact[i] = False
    out = m.drop(columns=["ranked"]).copy()
    out["rank"] = rank
    out["L"] = Lq
    out["r"] = rank / Lq
    out["r_desc"] = (Lq + 1 - rank) / Lq
    out["d"] = out["distance"].astype(float) if "distance" in out.columns else np.nan
    out["exact"] = exact
    out["place_size"] = psize
    return out, counts


def write_imported_ranks(
    path: Path,
    pairs: pd.DataFrame,
    frames: pd.DataFrame,
    radius_m: float,
    max_yaw_deg: float,
    tmp: Path,
) -> dict:
    """Read the user's rank file, score it against the pairs' places, write ``tmp/ranks.parquet``.

    Args:
        path: The rank file (parquet or CSV, schema above).
        pairs: The run's pairs.
        frames: The frame table (the places' frames).
        radius_m: The place radius, metres.
        max_yaw_deg: The place's heading limit, degrees.
        tmp: The entry's directory.

    Returns:
        The import counters (unmatched ids, rows without a place frame, ...).
    """
    df, counts = ranks_from_import(
        read_import(path), pairs, str(path), frames, radius_m, max_yaw_deg
    )
    write_parquet(tmp / "ranks.parquet", df)
    return counts

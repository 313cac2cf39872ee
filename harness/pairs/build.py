"""Cross-season pairs (SPEC section 4).

Each query frame's nearest-position reference in every other session among frames whose heading
differs by less than ``max_yaw_diff_deg``.
"""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from harness.pairs.config import PairsConfig
from harness.records import FRAME_KEY, IMAGE_KEY, QUERY_KEY
from harness.runtime.cache import write_json, write_parquet

log = logging.getLogger(__name__)

PAIR_COLUMNS = [
    "q_session",
    "q_camera",
    "q_utime",
    "r_session",
    "r_camera",
    "r_utime",
    "distance_m",
    "yaw_diff_deg",
    "season_pair",
]


def season_pairs(q_sessions: Any, r_session: str, seasons: dict[str, str]) -> list[str]:
    """``season_pair`` of each query session against ``r_session``: ``"WI->SU"``."""
    return [f"{seasons.get(s, s)}->{seasons.get(r_session, r_session)}" for s in q_sessions]


def yaw_diff_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Absolute heading difference in degrees, in [0, 180], wrap-around at +-180 handled."""
    d = (np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi
    return np.abs(np.degrees(d))


def thin_by_stride(xy: np.ndarray, stride_m: float) -> np.ndarray:
    """Indices (in time order) keeping at most one frame per ``stride_m`` metres of trajectory."""
    if stride_m <= 0 or len(xy) == 0:
        return np.arange(len(xy))
    keep = [0]
    travelled = 0.0
    for i in range(1, len(xy)):
        travelled += float(np.linalg.norm(xy[i] - xy[i - 1]))
        if travelled >= stride_m:
            keep.append(i)
            travelled = 0.0
    return np.array(keep)


def nearest_with_heading(
    ref_xy: np.ndarray,
    ref_yaw: np.ndarray,
    ref_utime: np.ndarray,
    q_xy: np.ndarray,
    q_yaw: np.ndarray,
    max_yaw_deg: float,
    max_dist: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    """For each query, the index of the nearest reference with heading difference < ``max_yaw_deg``.

    Ties in distance go to the earlier reference frame (smaller utime). Returns (index or -1,
    distance).
    A KD-tree is queried with a growing k until each query's answer is certain.
    """
    n, m = len(q_xy), len(ref_xy)
    best = np.full(n, -1, np.int64)
    best_d = np.full(n, np.inf)
    if m == 0 or n == 0:
        return best, best_d
    tree = cKDTree(ref_xy)
    bound = np.inf if max_dist is None else max_dist * (1 + 1e-12)
    todo = np.arange(n)
    k = min(16, m)
    while len(todo):
        d, idx = tree.query(q_xy[todo], k=k, distance_upper_bound=bound)
        d, idx = np.atleast_2d(d), np.atleast_2d(idx)
        if d.shape[0] != len(todo):  # k == 1 returns 1-D
            d, idx = d.T, idx.T
        valid = idx < m
        safe = np.where(valid, idx, 0)
        ok = valid & (yaw_diff_deg(q_yaw[todo][:, None], ref_yaw[safe]) < max_yaw_deg)
        dd = np.where(ok, d, np.inf)
        # tie-break by utime: sort key (distance, utime)
        ut = np.where(ok, ref_utime[safe], np.iinfo(np.int64).max)
        order = np.lexsort((ut, dd), axis=1)
        first = order[:, 0]
        rows = np.arange(len(todo))
        fd = dd[rows, first]
        exhausted = (k >= m) | ~valid[:, -1]  # every candidate within the bound was seen
        certain = exhausted | (np.isfinite(fd) & (fd < d[:, -1]))
        hit = certain & np.isfinite(fd)
        best[todo[hit]] = idx[rows, first][hit]
        best_d[todo[hit]] = fd[hit]
        todo = todo[~certain]
        k = min(m, k * 4)
    return best, best_d


def _query_frames(
    frames: pd.DataFrame, stride_m: float, queries: pd.DataFrame | None
) -> pd.DataFrame:
    """The query frames: the listed ones, else every frame thinned to one per ``stride_m``."""
    if queries is not None:
        return frames.merge(queries[FRAME_KEY].drop_duplicates(), on=FRAME_KEY, how="inner")
    parts = []
    for _, g in frames.groupby(["session", "camera"], sort=True):
        g = g.sort_values("utime")
        parts.append(g.iloc[thin_by_stride(g[["x", "y"]].to_numpy(), stride_m)])
    return pd.concat(parts, ignore_index=True) if parts else frames.iloc[:0]


def _summary(
    q_all: pd.DataFrame, pairs: pd.DataFrame, matched: Counter[str], unmatched: Counter[str]
) -> dict[str, Any]:
    """The pairing summary: queries, pairs, and the drops by season pair."""
    return {
        "queries": len(q_all),
        "pairs": len(pairs),
        "pairs_per_season_pair": dict(sorted(matched.items())),
        "no_reference_per_season_pair": dict(sorted(unmatched.items())),
        "queries_without_any_reference": int(
            len(q_all) - pairs[QUERY_KEY].drop_duplicates().shape[0]
        ),
    }


def build_pairs(
    frames: pd.DataFrame,
    cfg: PairsConfig,
    seasons: dict[str, str],
    queries: pd.DataFrame | None = None,
) -> tuple[pd.DataFrame, dict]:
    """Pairs of every query frame with each other session.

    Args:
        frames: the frame table (all sessions).
        cfg: pairing options.
        seasons: session -> season code, for ``season_pair``.
        queries: optional frame keys (session, camera, utime) restricting the query frames
            (the annotated ones); stride thinning applies only when this is None.

    Returns:
        (pairs table with PAIR_COLUMNS, summary dict with counts per season pair and unmatched
        queries).
    """
    frames = frames.sort_values(FRAME_KEY).reset_index(drop=True)
    q_all = _query_frames(frames, cfg.stride_m, queries)
    sessions = sorted(frames["session"].unique())
    out = []
    matched: Counter[str] = Counter()
    unmatched: Counter[str] = Counter()
    for rs in sessions:
        ref = frames[frames["session"] == rs].reset_index(drop=True)
        q = q_all[q_all["session"] != rs].reset_index(drop=True)
        if not len(q):
            continue
        idx, dist = nearest_with_heading(
            ref[["x", "y"]].to_numpy(),
            ref["yaw"].to_numpy(),
            ref["utime"].to_numpy(),
            q[["x", "y"]].to_numpy(),
            q["yaw"].to_numpy(),
            cfg.max_yaw_diff_deg,
            cfg.max_distance_m,
        )
        sp = season_pairs(q["session"], rs, seasons)
        for s, ok in zip(sp, idx >= 0, strict=True):
            (matched if ok else unmatched)[s] += 1
        hit = idx >= 0
        r = ref.iloc[idx[hit]].reset_index(drop=True)
        qh = q[hit].reset_index(drop=True)
        out.append(
            pd.DataFrame(
                {
                    "q_session": qh["session"],
                    "q_camera": qh["camera"],
                    "q_utime": qh["utime"],
                    "r_session": r["session"],
                    "r_camera": r["camera"],
                    "r_utime": r["utime"],
                    "distance_m": dist[hit],
                    "yaw_diff_deg": yaw_diff_deg(qh["yaw"].to_numpy(), r["yaw"].to_numpy()),
                    "season_pair": np.array(sp, dtype=object)[hit],
                }
            )
        )
    pairs = pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=PAIR_COLUMNS)
    pairs = pairs.sort_values(IMAGE_KEY).reset_index(drop=True)
    summary = _summary(q_all, pairs, matched, unmatched)
    log.info(
        "pairs: %d queries, %d pairs, %d (query, session) without reference",
        len(q_all),
        len(pairs),
        sum(unmatched.values()),
    )
    return pairs[PAIR_COLUMNS], summary


def candidate_pairs(
    frames: pd.DataFrame, seasons: dict[str, str], queries: pd.DataFrame | None = None
) -> pd.DataFrame:
    """Every query frame with every other session, before retrieval chooses the frame (SPEC 13.2).

    Args:
        frames: the frame table (all sessions; poses not needed).
        seasons: session -> season code, for ``season_pair``.
        queries: optional frame keys restricting the query frames (the annotated ones).

    Returns:
        ``q_session, q_camera, q_utime, r_session, season_pair``: one row per query frame and
        reference session; :func:`harness.retrieval.pairing.retrieval_pairs` adds the frame.
    """
    fr = frames.sort_values(FRAME_KEY).reset_index(drop=True)
    if queries is not None:
        fr = fr.merge(queries[FRAME_KEY].drop_duplicates(), on=FRAME_KEY, how="inner")
    out = []
    for rs in sorted(frames["session"].unique()):
        q = fr[fr["session"] != rs]
        out.append(
            pd.DataFrame(
                {
                    "q_session": q["session"].to_numpy(),
                    "q_camera": q["camera"].to_numpy(),
                    "q_utime": q["utime"].to_numpy(np.int64),
                    "r_session": rs,
                    "season_pair": season_pairs(q["session"], rs, seasons),
                }
            )
        )
    cols = [*IMAGE_KEY, "season_pair"]
    cand = pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=cols)
    return cand.sort_values([*QUERY_KEY, "r_session"]).reset_index(drop=True)[cols]


def write_pairs(
    frames: pd.DataFrame,
    cfg: PairsConfig,
    seasons: dict[str, str],
    queries: pd.DataFrame | None,
    names: pd.DataFrame | None,
    tmp: Path,
) -> dict:
    """Build the pairs into ``tmp/pairs.parquet`` and ``tmp/summary.json``.

    By pose (:func:`build_pairs`), or by name or order (:func:`declared_pairs`, with the frames'
    ``names``).

    Returns:
        The pairing summary (queries, pairs, drops by reason).
    """
    if cfg.by in DECLARED:
        if names is None:
            raise ValueError(f"[pairs] by = {cfg.by!r} needs the frames' file names")
        pairs, summary = declared_pairs(frames, names, cfg.by, seasons, queries)
    else:
        pairs, summary = build_pairs(frames, cfg, seasons, queries)
    write_parquet(tmp / "pairs.parquet", pairs)
    write_json(tmp / "summary.json", summary)
    return summary


#: The pairing modes of sessions without poses that the user declares (SPEC 13.2).
DECLARED = ("name", "order")
#: The pairing modes that pair with the run's localizer (SPEC 13.2).
BY_RETRIEVAL = ("retrieval", "sequence")


def declared_pairs(
    frames: pd.DataFrame,
    names: pd.DataFrame,
    by: str,
    seasons: dict[str, str],
    queries: pd.DataFrame | None = None,
) -> tuple[pd.DataFrame, dict]:
    """Pairs by file name or by order (SPEC 13.2), of every query frame with each other session.

    ``by = "name"``: the reference frame whose file has the query's file name without its folder
    and suffix (``a/0001.png`` pairs with ``b/0001.jpg``); ``by = "order"``: the i-th frame of
    each session in file-name order (a session's frames are in time order, and a folder's times
    increase with its file names). A query without such a frame is counted, not paired. The user
    declares these pairs: their ``pair_confidence`` is 1.

    Args:
        frames: the frame table (all sessions; poses not needed).
        names: ``session, camera, utime, name`` of the frames that have a file name.
        by: ``name`` or ``order``.
        seasons: session -> season code, for ``season_pair``.
        queries: optional frame keys restricting the query frames.

    Returns:
        (pairs with PAIR_COLUMNS and ``pair_confidence``, the summary).
    """
    fr = frames.sort_values(FRAME_KEY).reset_index(drop=True)
    fr = fr.merge(names[[*FRAME_KEY, "name"]], on=FRAME_KEY, how="left")
    fr["order"] = fr.groupby("session", sort=False).cumcount()
    fr["stem"] = [
        PurePosixPath(n).stem if isinstance(n, str) else None for n in fr["name"].to_numpy()
    ]
    q_all = (
        fr.merge(queries[FRAME_KEY].drop_duplicates(), on=FRAME_KEY, how="inner")
        if queries is not None
        else fr
    )
    on = "stem" if by == "name" else "order"
    out = []
    matched: Counter[str] = Counter()
    unmatched: Counter[str] = Counter()
    for rs in sorted(fr["session"].unique()):
        ref = fr[(fr["session"] == rs) & fr[on].notna()].drop_duplicates(on)
        q = q_all[q_all["session"] != rs]
        m = q.merge(ref[[on, "session", "camera", "utime"]], on=on, how="left", suffixes=("", "_r"))
        sp = season_pairs(m["session"], rs, seasons)
        hit = m["utime_r"].notna().to_numpy()
        for s, ok in zip(sp, hit, strict=True):
            (matched if ok else unmatched)[s] += 1
        h = m[hit]
        out.append(
            pd.DataFrame(
                {
                    "q_session": h["session"].to_numpy(),
                    "q_camera": h["camera"].to_numpy(),
                    "q_utime": h["utime"].to_numpy(np.int64),
                    "r_session": rs,
                    "r_camera": h["camera_r"].to_numpy(),
                    "r_utime": h["utime_r"].to_numpy(np.int64),
                    "distance_m": np.nan,
                    "yaw_diff_deg": np.nan,
                    "season_pair": np.array(sp, dtype=object)[hit],
                    "pair_confidence": 1.0,
                }
            )
        )
    cols = [*PAIR_COLUMNS, "pair_confidence"]
    pairs = pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=cols)
    pairs = pose_columns(pairs, fr).sort_values(IMAGE_KEY).reset_index(drop=True)[cols]
    summary = {**_summary(q_all, pairs, matched, unmatched), "by": by}
    log.info(
        "pairs by %s: %d queries, %d pairs, %d (query, session) without a map image of the same %s",
        by,
        len(q_all),
        len(pairs),
        sum(unmatched.values()),
        "name" if by == "name" else "place in the order",
    )
    return pairs, summary


def pose_columns(pairs: pd.DataFrame, frames: pd.DataFrame) -> pd.DataFrame:
    """``pairs`` with ``distance_m`` and ``yaw_diff_deg`` from the frames' poses (NaN without).

    For pairs not made by pose (by name, order, retrieval or sequence) where poses exist.
    """
    pose = frames.set_index(FRAME_KEY)[["x", "y", "yaw"]]
    q = pose.reindex(pd.MultiIndex.from_frame(pairs[QUERY_KEY].set_axis(FRAME_KEY, axis=1)))
    r = pose.reindex(
        pd.MultiIndex.from_frame(
            pairs[["r_session", "r_camera", "r_utime"]].set_axis(FRAME_KEY, axis=1)
        )
    )
    pairs = pairs.copy()
    pairs["distance_m"] = np.hypot(
        q["x"].to_numpy(np.float64) - r["x"].to_numpy(np.float64),
        q["y"].to_numpy(np.float64) - r["y"].to_numpy(np.float64),
    )
    pairs["yaw_diff_deg"] = yaw_diff_deg(
        q["yaw"].to_numpy(np.float64), r["yaw"].to_numpy(np.float64)
    )
    return pairs

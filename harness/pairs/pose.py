"""Cross-season pairs (method §4).

Each query frame's nearest-position reference in every other session among frames whose heading
differs by less than ``max_yaw_diff_deg``.
"""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from harness.pairs.config import PairsConfig
from harness.pairs.modes import PairingMode
from harness.pairs.table import (
    PAIR_COLUMNS,
    pairing_summary,
    season_pairs,
    yaw_diff_deg,
)
from harness.records import FRAME_KEY, IMAGE_KEY

log = logging.getLogger(__name__)


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
    summary = pairing_summary(q_all, pairs, matched, unmatched)
    log.info(
        "pairs: %d queries, %d pairs, %d (query, session) without reference",
        len(q_all),
        len(pairs),
        sum(unmatched.values()),
    )
    return pairs[PAIR_COLUMNS], summary


def _build(
    frames: pd.DataFrame,
    pc: PairsConfig,
    seasons: dict[str, str],
    queries: pd.DataFrame | None,
    names: pd.DataFrame | None,
) -> tuple[pd.DataFrame, dict]:
    """By pose: :func:`build_pairs` (file names are not read)."""
    del names
    return build_pairs(frames, pc, seasons, queries)


#: This module's pairing mode.
MODES = (PairingMode("pose", "pose", build=_build),)

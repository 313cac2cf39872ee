"""The ground-truth place P(G) of a reference frame (method §6): near frames facing its way."""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from harness.pairs.table import yaw_diff_deg


def ground_truth_places(
    ref_frames: pd.DataFrame, gt_utime: np.ndarray, radius_m: float, max_yaw_deg: float
) -> dict[int, np.ndarray]:
    """The ground-truth place P(G) of each reference frame G (method §6).

    P(G) = the frames of the reference session within ``radius_m`` metres of G's position whose
    heading differs from G's by less than ``max_yaw_deg`` degrees; G itself always belongs to it.
    ``radius_m = 0`` gives P(G) = {G}.

    Args:
        ref_frames: the reference session's frames (``utime, x, y, yaw``; one camera).
        gt_utime: the ground-truth frames G whose place is wanted.
        radius_m: the place's radius, metres.
        max_yaw_deg: the largest heading difference from G, degrees.

    Returns:
        G's utime -> sorted utimes of P(G).
    """
    out: dict[int, np.ndarray] = {}
    uniq = np.unique(np.asarray(gt_utime, np.int64))
    if radius_m <= 0 or not len(ref_frames):
        return {int(g): np.array([g], np.int64) for g in uniq}
    ref = ref_frames.sort_values("utime")
    ut = ref["utime"].to_numpy(np.int64)
    xy = ref[["x", "y"]].to_numpy(np.float64)
    yaw = ref["yaw"].to_numpy(np.float64)
    tree = cKDTree(xy)
    pos = np.searchsorted(ut, uniq)
    for g, p in zip(uniq, pos, strict=True):
        if p >= len(ut) or ut[p] != g:
            out[int(g)] = np.array([g], np.int64)
            continue
        near = np.array(tree.query_ball_point(xy[p], r=radius_m), np.int64)
        near = near[yaw_diff_deg(yaw[near], yaw[p]) < max_yaw_deg] if len(near) else near
        out[int(g)] = np.union1d(ut[near], [g]).astype(np.int64)
    return out


def places_by_order(
    ref_frames: pd.DataFrame, gt_utime: np.ndarray, place_frames: int
) -> dict[int, np.ndarray]:
    """The ground-truth place without poses (method §13.2): G and ``place_frames`` frames each side.

    The neighbours are taken in the reference session's time order (one camera), so the place is
    the stretch of the map around the frame a query was paired with by retrieval.

    Args:
        ref_frames: the reference session's frames (``utime``; one camera).
        gt_utime: the ground-truth frames G whose place is wanted.
        place_frames: neighbours on each side (0: G alone).

    Returns:
        G's utime -> sorted utimes of P(G).
    """
    ut = np.sort(ref_frames["utime"].to_numpy(np.int64))
    out: dict[int, np.ndarray] = {}
    for g in np.unique(np.asarray(gt_utime, np.int64)):
        p = int(np.searchsorted(ut, g))
        if p >= len(ut) or ut[p] != g:
            out[int(g)] = np.array([g], np.int64)
            continue
        out[int(g)] = ut[max(0, p - place_frames) : p + place_frames + 1].copy()
    return out

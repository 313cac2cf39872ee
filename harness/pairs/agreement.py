"""How often pairs by retrieval agree with the pairs by pose, where poses exist (method §13.2)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from harness.records import FRAME_KEY, QUERY_KEY


def pose_agreement(
    by_retrieval: pd.DataFrame, by_pose: pd.DataFrame, frames: pd.DataFrame, within_m: float
) -> dict[str, Any]:
    """How often the retrieval pair is where the pose pair is (method §13.2), where poses exist.

    A retrieval pair agrees when its reference frame lies within ``within_m`` metres of the pose
    pair's reference frame (same query frame, same reference session).

    Returns:
        ``compared`` (query frames with both pairs), ``agree``, ``share`` (NaN when none was
        compared) with its exact 95% interval ``share_ci_low`` / ``share_ci_high``
        (Clopper-Pearson), ``chance_share`` (the share a map frame drawn uniformly from the
        reference session would reach: the mean, over the compared pairs, of the share of that
        session's frames within ``within_m`` of the pose pair's frame), ``median_m`` (the median
        distance between the two reference frames), ``within_m``.
    """
    from scipy.special import betaincinv  # scipy.stats.beta.ppf's values, without scipy.stats

    keys = [*QUERY_KEY, "r_session"]
    m = by_retrieval[[*keys, "r_camera", "r_utime"]].merge(
        by_pose[[*keys, "r_camera", "r_utime"]], on=keys, suffixes=("", "_pose")
    )
    pose = frames.set_index(FRAME_KEY)[["x", "y"]]

    def xy(cam: str, ut: str) -> np.ndarray:
        idx = pd.MultiIndex.from_arrays([m["r_session"], m[cam], m[ut]], names=FRAME_KEY)
        return np.asarray(pose.reindex(idx).to_numpy(np.float64), np.float64)

    dist = np.linalg.norm(xy("r_camera", "r_utime") - xy("r_camera_pose", "r_utime_pose"), axis=1)
    ok = np.isfinite(dist)
    agree, n = int((dist[ok] <= within_m).sum()), int(ok.sum())
    pose_xy = xy("r_camera_pose", "r_utime_pose")[ok]
    chance = []
    for s, pxy in zip(m["r_session"].to_numpy()[ok], pose_xy, strict=True):
        ref = frames.loc[frames["session"] == s, ["x", "y"]].to_numpy(np.float64)
        chance.append(float((np.linalg.norm(ref - pxy, axis=1) <= within_m).mean()))
    lo = float(betaincinv(agree, n - agree + 1, 0.025)) if agree > 0 else 0.0
    hi = float(betaincinv(agree + 1, n - agree, 0.975)) if agree < n else 1.0
    return {
        "compared": n,
        "agree": agree,
        "share": round(agree / n, 4) if n else float("nan"),
        "share_ci_low": round(lo, 4) if n else float("nan"),
        "share_ci_high": round(hi, 4) if n else float("nan"),
        "chance_share": round(float(np.mean(chance)), 4) if n else float("nan"),
        "median_m": round(float(np.median(dist[ok])), 3) if ok.any() else float("nan"),
        "within_m": within_m,
    }

"""The pair table's shape, shared by every pairing mode (method §4, 13.2).

Its columns, the season pairs, heading differences, the summary, and the pose columns of pairs
made without poses.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import pandas as pd

from harness.records import FRAME_KEY, QUERY_KEY

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


def pairing_summary(
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

"""Pairs the user declares (method §13.2): by file name or by order, for sessions without poses."""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import PurePosixPath

import numpy as np
import pandas as pd

from harness.pairs.config import PairsConfig
from harness.pairs.modes import PairingMode
from harness.pairs.table import (
    PAIR_COLUMNS,
    pairing_summary,
    pose_columns,
    season_pairs,
)
from harness.records import FRAME_KEY, IMAGE_KEY

log = logging.getLogger(__name__)


def declared_pairs(
    frames: pd.DataFrame,
    names: pd.DataFrame,
    by: str,
    seasons: dict[str, str],
    queries: pd.DataFrame | None = None,
) -> tuple[pd.DataFrame, dict]:
    """Pairs by file name or by order (method §13.2), of every query frame with each other session.

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
    summary = {**pairing_summary(q_all, pairs, matched, unmatched), "by": by}
    log.info(
        "pairs by %s: %d queries, %d pairs, %d (query, session) without a map image of the same %s",
        by,
        len(q_all),
        len(pairs),
        sum(unmatched.values()),
        "name" if by == "name" else "place in the order",
    )
    return pairs, summary


def _build(
    frames: pd.DataFrame,
    pc: PairsConfig,
    seasons: dict[str, str],
    queries: pd.DataFrame | None,
    names: pd.DataFrame | None,
) -> tuple[pd.DataFrame, dict]:
    """By name or order: :func:`declared_pairs` on the frames' file names."""
    if names is None:
        raise ValueError(f"[pairs] by = {pc.by!r} needs the frames' file names")
    return declared_pairs(frames, names, pc.by, seasons, queries)


#: This module's pairing modes (method §13.2), the user's declaration through file names.
MODES = (
    PairingMode("name", "declared", "the map image of the same file name", _build),
    PairingMode("order", "declared", "the map image at the same place in file-name order", _build),
)

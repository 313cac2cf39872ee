"""``harness detect``'s figures: the trajectory with the most changed places, the score timeline."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.records import FRAME_KEY


def has_poses(frames: pd.DataFrame) -> bool:
    """Whether every frame has a position (not a session of images alone, method §13.2)."""
    return bool(len(frames)) and bool(frames[["x", "y"]].notna().all(axis=None))


def trajectory_figure(
    path: Path, frames: pd.DataFrame, map_session: str, fr: pd.DataFrame, top: pd.DataFrame
) -> Path:
    """The map session's path in grey, the query frames coloured by change score, top numbered.

    Without poses (method §13.2): the change score of each query frame in time order, top numbered.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not has_poses(frames):
        return _score_timeline(path, fr, top, plt)
    m = frames[frames["session"] == map_session].sort_values("utime")
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.plot(m["x"], m["y"], "-", color="0.7", lw=3, label=f"map {map_session}", zorder=1)
    sc = ax.scatter(
        fr["x"], fr["y"], c=fr["score"], cmap="inferno", s=18, zorder=2, label="query frames"
    )
    for i, r in enumerate(top.itertuples(), start=1):
        ax.annotate(
            str(i),
            (r.x, r.y),
            xytext=(4, 4),
            textcoords="offset points",
            fontsize=9,
            weight="bold",
            color="#1060c0",
        )
    fig.colorbar(sc, ax=ax, label="change score (largest LoC of the frame)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Query trajectory over the map; numbers: the most changed places")
    return _save(fig, path, plt)


def _score_timeline(path: Path, fr: pd.DataFrame, top: pd.DataFrame, plt: Any) -> Path:
    """Each query frame's change score in time order (no poses), the most changed numbered."""
    order = fr.sort_values(FRAME_KEY).reset_index(drop=True)
    pos = {
        k: i
        for i, k in enumerate(zip(order["session"], order["camera"], order["utime"], strict=True))
    }
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(np.arange(len(order)), order["score"], "-", color="0.6", lw=1, zorder=1)
    sc = ax.scatter(
        np.arange(len(order)), order["score"], c=order["score"], cmap="inferno", s=18, zorder=2
    )
    for i, r in enumerate(top.itertuples(), start=1):
        j = pos.get((r.session, r.camera, r.utime))
        if j is not None:
            ax.annotate(str(i), (j, r.score), xytext=(4, 4), textcoords="offset points",
                        fontsize=9, weight="bold", color="#1060c0")  # fmt: skip
    fig.colorbar(sc, ax=ax, label="change score")
    ax.set_xlabel("query frame (time order)")
    ax.set_ylabel("change score (largest LoC)")
    ax.set_title("No poses: change score along the query sequence; numbers: most changed")
    return _save(fig, path, plt)


def _save(fig: Any, path: Path, plt: Any) -> Path:
    """Write ``fig`` to ``path`` atomically (a temporary beside it, renamed) and close it."""
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.dbl-harness.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path

"""The layout every rank engine reads (method §6), and :class:`Ranks`, what each returns.

Each database row's frame, the frames' rows, and each query's place columns.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from harness.errors import RetrievalError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Ranks:
    """Per query subimage: rank of its ground-truth place, list length, distance, place size."""

    rank: np.ndarray  # (n,) int64
    L: np.ndarray  # (n,) int64: 1 + frames outside the ground-truth place
    dist: np.ndarray  # (n,) float64
    exact: np.ndarray  # (n,) bool: False where an approximate engine could only bound the rank
    place_size: np.ndarray  # (n,) int64: frames of the place that are in the database


def place_columns(
    frame_ids: np.ndarray, gt_frame: np.ndarray, place: Sequence[np.ndarray] | None
) -> list[np.ndarray]:
    """Per query, the database columns (sorted frame ids) of its ground-truth place.

    G must be present.
    """
    L = len(frame_ids)
    col = np.searchsorted(frame_ids, gt_frame)
    if L == 0 or np.any(col >= L) or np.any(frame_ids[np.minimum(col, L - 1)] != gt_frame):
        raise RetrievalError("a ground-truth frame has no subimage in the database")
    if place is None:
        return [np.array([c]) for c in col]
    if len(place) != len(gt_frame):
        raise RetrievalError(
            f"place must hold one entry per query ({len(gt_frame)}), got {len(place)}"
        )
    out = []
    for c, p in zip(col, place, strict=True):
        p = np.asarray(p)
        pc = np.searchsorted(frame_ids, p)
        ok = (pc < L) & (frame_ids[np.minimum(pc, L - 1)] == p)
        out.append(
            np.union1d(pc[ok], [c])
        )  # frames of the place without subimages are not in the list
    return out


def frame_layout(db_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order of database rows grouped by frame, the frame ids in that order, and group starts."""
    order = np.argsort(db_frame, kind="stable")
    f = db_frame[order]
    starts = (
        np.concatenate([[0], np.nonzero(f[1:] != f[:-1])[0] + 1])
        if len(f)
        else np.zeros(0, np.int64)
    )
    return order, f[starts], starts

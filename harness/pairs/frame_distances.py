"""The frames' distance matrix of pairs without poses, streamed, and SeqSLAM's sequence score.

The distance of a query frame to a map frame is the mean, over the query's subimages of one
proposal method, of the smallest squared L2 distance to that map frame's subimages
(:mod:`harness.pairs.retrieval`); the matrix is streamed in groups of query frames against
chunks of whole map frames, so its memory is bounded by a budget whatever the sessions' sizes.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import numpy as np


def frame_blocks(frame_of_row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(frame ids in row order, start row of each) of rows already grouped by frame."""
    change = np.r_[True, frame_of_row[1:] != frame_of_row[:-1]]
    starts = np.nonzero(change)[0]
    return frame_of_row[starts], starts


def mean_blocks(
    q_desc: np.ndarray,
    q_frame: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    chunk_rows: int,
    memory_mb: float,
) -> Iterator[tuple[np.ndarray, np.ndarray, int, int, np.ndarray]]:
    """The frame distances of each group of query frames, the database streamed in chunks.

    Yields (query frame ids, database frame ids, g0, g1, the (g1 - g0, n_db) distances): the
    mean over a query frame's rows of the least squared distance to each database frame's rows.
    """
    qf_ids, q_starts = frame_blocks(np.asarray(q_frame))
    db_ids, db_starts = frame_blocks(np.asarray(db_frame))
    q_row_frame = np.repeat(np.arange(len(qf_ids)), np.diff(np.r_[q_starts, len(q_frame)]))
    q_count = np.bincount(q_row_frame, minlength=len(qf_ids)).astype(np.float64)
    group = max(1, int(memory_mb * 2**20 // max(8 * len(db_ids), 1)))
    db_cuts = [0]  # frame indices where a chunk starts
    for i, s in enumerate(db_starts):
        if s - db_starts[db_cuts[-1]] >= chunk_rows:
            db_cuts.append(i)
    db_cuts.append(len(db_ids))
    bounds = np.r_[db_starts, len(db_frame)]
    q_bounds = np.r_[q_starts, len(q_frame)]
    for g0 in range(0, len(qf_ids), group):
        g1 = min(len(qf_ids), g0 + group)
        r0, r1 = int(q_bounds[g0]), int(q_bounds[g1])
        q = np.asarray(q_desc[r0:r1], np.float32)
        qn = (q.astype(np.float64) ** 2).sum(1)
        sums = np.zeros((g1 - g0, len(db_ids)), np.float64)
        rows_frame = q_row_frame[r0:r1] - g0
        for c0, c1 in itertools.pairwise(db_cuts):
            a, b = int(bounds[c0]), int(bounds[c1])
            blk = np.asarray(db_desc[a:b], np.float32)
            d2 = qn[:, None] + (blk.astype(np.float64) ** 2).sum(1)[None, :] - 2.0 * (q @ blk.T)
            mins = np.minimum.reduceat(np.maximum(d2, 0.0), bounds[c0:c1] - a, axis=1)
            np.add.at(sums[:, c0:c1], rows_frame, mins)
        yield qf_ids, db_ids, g0, g1, sums / q_count[g0:g1, None]


#: The speeds (map frames per query frame) a sequence may run at (SeqSLAM's velocity range).
SEQUENCE_SPEEDS = (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)


def sequence_scores(mean: np.ndarray, window: int) -> np.ndarray:
    """SeqSLAM's sequence score of every (query frame, map frame) pair (method §13.2).

    ``mean`` is the (n_q, n_db) frame distance matrix, both sessions in time order. The score of
    (i, j) is the least, over the speeds :data:`SEQUENCE_SPEEDS`, of the mean distance along the
    straight line through (i, j) over the ``window`` query frames centred on i (the map frame of
    query frame ``i + k`` being ``j + round(v k)``); frames past either end take no part.
    """
    nq, nd = mean.shape
    half = max(window, 1) // 2
    best = np.full((nq, nd), np.inf)
    for v in SEQUENCE_SPEEDS:
        acc = np.zeros((nq, nd))
        cnt = np.zeros((nq, nd))
        for k in range(-half, half + 1):
            off = round(v * k)
            i0, i1 = max(0, -k), min(nq, nq - k)  # rows i with i + k inside
            j0, j1 = max(0, -off), min(nd, nd - off)
            if i0 >= i1 or j0 >= j1:
                continue
            acc[i0:i1, j0:j1] += mean[i0 + k : i1 + k, j0 + off : j1 + off]
            cnt[i0:i1, j0:j1] += 1
        best = np.minimum(best, np.divide(acc, cnt, out=np.full((nq, nd), np.inf), where=cnt > 0))
    return best

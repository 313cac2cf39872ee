"""Pairs without poses (method §13.2): each query frame's map frame by image-level retrieval.

A query frame is paired, in each other session, with the frame its subimages retrieve best with
the run's localizer: the frame distance is the mean, over the query's subimages of one proposal
method (``grid5`` by default: the same five boxes in every frame), of the smallest squared L2
distance to that frame's subimages of the method, and the frame of least distance is the pair.
Streamed: query frames in groups, the reference database in chunks of whole frames, so memory is
bounded by ``memory_mb`` whatever the sessions' sizes.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.pairs.frame_distances import frame_blocks, mean_blocks
from harness.pairs.modes import PairingMode
from harness.pairs.place import no_place_summary, without_no_place
from harness.pairs.sequence import banded_pairs, path_pairs
from harness.pairs.table import PAIR_COLUMNS, pose_columns, season_pairs
from harness.records import FRAME_KEY, IMAGE_KEY, QUERY_KEY
from harness.runtime.cache import read_cached_parquet, write_json, write_parquet


def _best_and_rival(mean: np.ndarray, exclude: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(argmin, min, the least value more than ``exclude`` columns from the argmin) per row."""
    arg = np.argmin(mean, axis=1)
    pos = np.arange(mean.shape[1])
    rival = np.where(np.abs(pos[None, :] - arg[:, None]) > exclude, mean, np.inf)
    second = rival.min(axis=1) if rival.shape[1] else np.full(len(mean), np.inf)
    return arg, mean[np.arange(len(mean)), arg], second


def best_frames(
    q_desc: np.ndarray,
    q_frame: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    *,
    chunk_rows: int = 8192,
    memory_mb: float = 256.0,
    exclude: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each query frame's best database frame by mean per-frame minimum squared distance.

    Also the runner-up: the least distance among the database frames more than ``exclude``
    frames away from the best one in database order (its own place's neighbours are no rival),
    inf where there is none.

    Args:
        q_desc: (n, D) query subimage descriptors, rows grouped by frame.
        q_frame: (n,) the frame id of each query row.
        db_desc: (m, D) database subimage descriptors (array or float16 memmap), grouped by frame.
        db_frame: (m,) the frame id of each database row.
        chunk_rows: database rows per pass (cut at frame boundaries).
        memory_mb: budget of the (query frames x database frames) sums.
        exclude: the runner-up lies more than this many frames from the best one.

    Returns:
        (query frame ids, their best database frame ids, the best mean squared distance, the
        runner-up's).
    """
    qf_ids, _ = frame_blocks(np.asarray(q_frame))
    best = np.zeros(len(qf_ids), np.int64)
    score = np.zeros(len(qf_ids), np.float64)
    second = np.full(len(qf_ids), np.inf)
    for _, db_ids, g0, g1, mean in mean_blocks(
        q_desc, q_frame, db_desc, db_frame, chunk_rows, memory_mb
    ):
        arg, score[g0:g1], second[g0:g1] = _best_and_rival(mean, exclude)
        best[g0:g1] = db_ids[arg]
    return qf_ids, best, score, second


def sequence_frames(
    q_desc: np.ndarray,
    q_frame: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    *,
    window: int,
    usable: np.ndarray | None = None,
    memory_mb: float = 256.0,
    exclude: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[int, str]]:
    """Each query frame's map frame by one order-keeping alignment of the two runs.

    :func:`harness.pairs.sequence.path_pairs` over the (query frames x map frames) distances,
    both in time order, and SeqSLAM's sequence scores of ``window`` frames
    (:func:`harness.pairs.frame_distances.sequence_scores`); ``usable``: the map frames (by
    position) that carry a place (None: all).

    Returns (query frame ids, their map frame ids, the path's scores, the rivals', and the query
    frames left unpaired, by position, with why). The distances are held (8 bytes a cell) with
    the path's back-pointers (1 byte) within ``memory_mb``; over it the path is found in a band
    around a coarse one, the distances streamed
    (:func:`harness.pairs.sequence.banded_pairs`).
    """
    qf_ids, _ = frame_blocks(np.asarray(q_frame))
    db_ids, _ = frame_blocks(np.asarray(db_frame))
    ok = np.ones(len(db_ids), bool) if usable is None else np.asarray(usable, bool)
    if 9 * len(qf_ids) * len(db_ids) / 2**20 > memory_mb:  # a long ride: banded, streamed

        def rows(pos: np.ndarray) -> Iterator[np.ndarray]:
            want = np.isin(q_frame, qf_ids[pos])
            for *_, m in mean_blocks(
                q_desc[want], q_frame[want], db_desc, db_frame, 8192, memory_mb / 4
            ):
                yield m

        budget = int(memory_mb * 2**20 / 4 / 8)  # a quarter of the budget for the coarse path
        found = banded_pairs(rows, (len(qf_ids), len(db_ids)), ok, window, exclude, budget)
    else:
        mean = np.zeros((len(qf_ids), len(db_ids)))
        for _, _, g0, g1, m in mean_blocks(q_desc, q_frame, db_desc, db_frame, 8192, memory_mb):
            mean[g0:g1] = m
        found = path_pairs(mean, ok, window, exclude)
    col, score, second, unpaired = found
    return qf_ids, db_ids[col], score, second, unpaired


def pair_confidence(best: np.ndarray, second: np.ndarray) -> np.ndarray:
    """``1 - best / runner-up`` of squared distances, in [0, 1] (method §13.2).

    0 where another place matches as well as the chosen one, 1 where the best match is exact;
    1 without a rival.
    """
    b, s = np.asarray(best, np.float64), np.asarray(second, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(np.isfinite(s) & (s > 0), 1.0 - b / s, 1.0)
    return np.clip(c, 0.0, 1.0)


def retrieval_pairs(
    candidates: pd.DataFrame,
    descriptors: dict[str, Path],
    frames: pd.DataFrame,
    proposer: str,
    memory_mb: float = 256.0,
    place_frames: int = 2,
    window: int = 0,
    min_place_contrast: float = 0.0,
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Pair each candidate query frame with its best frame of each reference session.

    Each pair's ``pair_confidence`` (:func:`pair_confidence`) compares its distance with the
    best frame's outside the pair's place (``place_frames`` each side). Frames whose contrast is
    under ``min_place_contrast`` carry no place (:mod:`harness.pairs.place`): no map frame of
    theirs is a candidate, no query frame of theirs gets a pair; the summary names them.

    Args:
        candidates: query frames and the reference sessions to pair them with (``q_session``,
            ``q_camera``, ``q_utime``, ``r_session``, ``r_camera``, ``season_pair``).
        descriptors: each session's descriptor entry (``desc.npy`` + ``index.parquet``).
        frames: the frame table (poses, where there are, give ``distance_m`` and ``yaw_diff_deg``).
        proposer: the proposal method whose subimages compare frames.
        memory_mb: the budget of one group's frame sums.
        place_frames: the pair's place, frames each side (no rival for the confidence).
        window: 0: each query frame alone (``by = "retrieval"``); else the query frames of a
            sequence window (``by = "sequence"``, :func:`sequence_frames`).
        min_place_contrast: frames of lower contrast carry no place (0: every frame does).

    Returns:
        (pairs with ``PAIR_COLUMNS`` plus ``retrieval_d2``, a summary of counts).
    """
    out = []
    no_subimage = 0
    unpaired: list[dict[str, Any]] = []  # sequence: query frames the path leaves unpaired
    candidates, blank, keys = without_no_place(candidates, frames, min_place_contrast)
    for (qs, rs), cand in candidates.groupby(["q_session", "r_session"], sort=True):
        qi = read_cached_parquet(descriptors[qs] / "index.parquet")
        ri = read_cached_parquet(descriptors[rs] / "index.parquet")
        qsel = qi[qi["proposal_method"] == proposer].reset_index()
        want = pd.MultiIndex.from_frame(cand[QUERY_KEY].set_axis(FRAME_KEY, axis=1))
        qsel = qsel[pd.MultiIndex.from_frame(qsel[FRAME_KEY]).isin(want)]
        rsel = ri[ri["proposal_method"] == proposer].reset_index()
        if blank and not window:  # a map frame that carries no place is nobody's pair; in a
            # sequence it keeps its place in the map's order, and the path runs through it
            rsel = rsel[~pd.MultiIndex.from_frame(rsel[FRAME_KEY]).isin(keys)]
        if not len(qsel) or not len(rsel):
            no_subimage += len(cand)
            continue
        qsel = qsel.sort_values([*FRAME_KEY, "box_id"], kind="stable")
        rsel = rsel.sort_values([*FRAME_KEY, "box_id"], kind="stable")
        q_ids = qsel.groupby(["camera", "utime"], sort=False).ngroup().to_numpy()
        r_ids = rsel.groupby(["camera", "utime"], sort=False).ngroup().to_numpy()
        qdesc = np.load(descriptors[qs] / "desc.npy", mmap_mode="r")
        rdesc = np.load(descriptors[rs] / "desc.npy", mmap_mode="r")
        args = (qdesc[qsel["index"].to_numpy()], q_ids, rdesc[rsel["index"].to_numpy()], r_ids)
        before = len(unpaired)
        if window:
            qf, bf, d2, d2_second = _by_sequence(
                args, qsel, rsel, keys, (window, memory_mb, place_frames), unpaired
            )
        else:
            qf, bf, d2, d2_second = best_frames(*args, memory_mb=memory_mb, exclude=place_frames)
        no_subimage += len(cand) - len(qf) - (len(unpaired) - before)
        part = _pair_rows(qs, rs, qsel, rsel, qf, bf, d2, d2_second)
        part = part.merge(
            cand[[*QUERY_KEY, "r_session", "season_pair"]], on=[*QUERY_KEY, "r_session"]
        )
        out.append(part)
    pairs = pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=PAIR_COLUMNS)
    pairs = pose_columns(pairs, frames).sort_values([*QUERY_KEY, "r_session"])
    pairs = pairs.reset_index(drop=True)
    summary = _summary(window, proposer, candidates, pairs, no_subimage, blank, min_place_contrast)
    if window:
        summary["unpaired"] = unpaired
    return pairs[[*PAIR_COLUMNS, "retrieval_d2", "pair_confidence"]], summary


def _by_sequence(
    args: tuple[np.ndarray, ...],
    qsel: pd.DataFrame,
    rsel: pd.DataFrame,
    keys: pd.MultiIndex | None,
    how: tuple[int, float, int],
    unpaired: list[dict[str, Any]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`sequence_frames` of one pair of sessions.

    The frames it leaves unpaired go to ``unpaired``, named by their keys; ``how``: the window,
    the memory budget and the place's frames.
    """
    window, memory_mb, place_frames = how
    none = pd.MultiIndex.from_tuples([], names=FRAME_KEY)
    maps = rsel.drop_duplicates(["camera", "utime"])[FRAME_KEY]
    usable = ~pd.MultiIndex.from_frame(maps).isin(keys if keys is not None else none)
    qf, bf, d2, d2_second, left = sequence_frames(
        *args, window=window, usable=usable, memory_mb=memory_mb, exclude=place_frames
    )
    qkeys = qsel.drop_duplicates(["camera", "utime"])[["session", "camera", "utime"]].to_numpy()
    for i, why in sorted(left.items()):
        unpaired.append({"session": str(qkeys[qf[i], 0]), "camera": str(qkeys[qf[i], 1]),
                         "utime": int(qkeys[qf[i], 2]), "why": why})  # fmt: skip
    keep = np.setdiff1d(np.arange(len(qf)), np.fromiter(left, np.int64, len(left)))
    return qf[keep], bf[keep], d2[keep], d2_second[keep]


def _summary(
    window: int,
    proposer: str,
    candidates: pd.DataFrame,
    pairs: pd.DataFrame,
    no_subimage: int,
    blank: dict,
    min_place_contrast: float,
) -> dict[str, Any]:
    """The pairs' ``summary.json``: the mode, the counts and the frames that carry no place."""
    return {
        "by": "sequence" if window else "retrieval",
        "proposal_method": proposer,
        "queries": int(candidates[QUERY_KEY].drop_duplicates().shape[0]),
        "pairs": len(pairs),
        "no_subimage": int(no_subimage),
        "no_place": no_place_summary(blank, min_place_contrast),
    }


def _pair_rows(
    qs: str,
    rs: str,
    qsel: pd.DataFrame,
    rsel: pd.DataFrame,
    qf: np.ndarray,
    bf: np.ndarray,
    d2: np.ndarray,
    d2_second: np.ndarray,
) -> pd.DataFrame:
    """The pairs of one (query session, map session) from the frame ids the matching chose."""
    qkeys = qsel.drop_duplicates(["camera", "utime"])[["camera", "utime"]].to_numpy()
    rkeys = rsel.drop_duplicates(["camera", "utime"])[["camera", "utime"]].to_numpy()
    return pd.DataFrame(
        {
            "q_session": qs,
            "q_camera": qkeys[qf, 0].astype(str),
            "q_utime": qkeys[qf, 1].astype(np.int64),
            "r_session": rs,
            "r_camera": rkeys[bf, 0].astype(str),
            "r_utime": rkeys[bf, 1].astype(np.int64),
            "retrieval_d2": d2,
            "pair_confidence": pair_confidence(d2, d2_second),
        }
    )


def write_retrieval_pairs(
    candidates: pd.DataFrame,
    descriptors: dict[str, Path],
    frames: pd.DataFrame,
    proposer: str,
    options: dict[str, Any],
    tmp: Path,
) -> dict[str, Any]:
    """:func:`retrieval_pairs` into ``tmp/pairs.parquet`` and ``tmp/summary.json``.

    ``options``: its keyword options (``memory_mb``, ``place_frames``, ``window``,
    ``min_place_contrast``).
    """
    pairs, summary = retrieval_pairs(candidates, descriptors, frames, proposer, **options)
    write_parquet(tmp / "pairs.parquet", pairs)
    write_json(tmp / "summary.json", summary)
    return summary


def candidate_pairs(
    frames: pd.DataFrame, seasons: dict[str, str], queries: pd.DataFrame | None = None
) -> pd.DataFrame:
    """Every query frame with every other session, before retrieval chooses (method §13.2).

    Args:
        frames: the frame table (all sessions; poses not needed).
        seasons: session -> season code, for ``season_pair``.
        queries: optional frame keys restricting the query frames (the annotated ones).

    Returns:
        ``q_session, q_camera, q_utime, r_session, season_pair``: one row per query frame and
        reference session; :func:`harness.pairs.retrieval.retrieval_pairs` adds the frame.
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


#: This module's pairing modes (method §13.2): the run's localizer chooses the map frame.
MODES = (
    PairingMode("retrieval", "retrieval", "the map frame this localizer retrieves best"),
    PairingMode(
        "sequence",
        "retrieval",
        "the map frame this localizer retrieves best over a run of consecutive frames",
        sequence=True,
    ),
)

"""Bring your own localizer: external ranked lists checked and scored as method §12 says.

Input (parquet or CSV), one row per query subimage:

| column | type | meaning |
|---|---|---|
| ``q_session, q_camera, q_utime`` | str, str, int | the query frame (``utime`` in microseconds) |
| ``proposal_method`` | str | the proposal method of the subimage (old name ``method``: warned) |
| ``box_id`` | int | the subimage's id within the frame and proposal method |
| ``x1, y1, x2, y2`` | float | the subimage box in upright pixels (x2, y2 exclusive) |
| ``r_session`` | str | the reference session searched (the pair's) |
| ``ranked`` | list of int (parquet) or space-separated ints (CSV) | reference frame utimes, best
first; may be truncated; never empty |
| ``L`` | int | the length of the full ranked list (the frames in the localizer's database) |
| ``scores`` | list of float (parquet) or space-separated floats (CSV), optional | the localizer's
score of each listed frame, parallel to ``ranked``; ``[import] score_kind`` says whether it is a
``distance`` (smaller = more similar) or a ``similarity`` in [0, 1] |

``harness task export`` writes the task these rows answer (the query subimages with the pair's
reference session, the reference frames with their boxes) and this schema beside it.

Scoring (the built-in engine's rules, method §6). The ground-truth reference G of a query
frame comes from the pair table and its *place* P(G) from the reference frames' poses. With
``scores``, each listed frame F has ``dist(F)`` (the score, or ``1 - s`` for a similarity), ``d`` is
the best ``dist`` over the listed frames of P(G), and ``rank = 1 +`` the number of listed frames
outside P(G) with ``dist < d`` (equal scores tie in the query's favour). Without ``scores`` the
list is a strict order: ``rank = 1 +`` the listed frames outside P(G) before the first frame of
P(G), and the localizer has no ``d`` (the score-fusion methods are not computed). ``L' = 1 +
L - |P(G) in the database|`` (the database: the reference frames that hold a box of the method).
A place absent from a truncated list gets the bound ``rank = min(L', len(ranked) + 1)`` (and, with
scores, the bound ``d`` = the last listed distance), marked ``exact = False`` and counted.

Every row must match a pair and a proposal of the run. Rows that match no pair or no proposal,
duplicate rows, ids that are not frames of the reference session, non-finite or out-of-order
scores, a list longer than ``L`` and a complete list without the place are errors that name the
file, the count and one example row.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.errors import RetrievalError
from harness.records import IMAGE_KEY, QUERY_KEY, SUBIMAGE_KEY
from harness.retrieval.import_file import BOX, KEY, SCORE_KINDS, ImportSpec, Rows, read_import
from harness.retrieval.places import ground_truth_places
from harness.runtime.cache import write_parquet

log = logging.getLogger(__name__)

#: A box that differs from the run's proposal by more than this many pixels is another box.
BOX_TOLERANCE_PX = 0.5


# ---------------------------------------------------------------------------- reading


# ---------------------------------------------------------------------------- scoring


def _distances(scores: list[float], kind: str) -> np.ndarray:
    d = np.asarray(scores, np.float64)
    return d if kind == "distance" else 1.0 - d


def _check_against_run(
    df: pd.DataFrame,
    rows: Rows,
    pairs: pd.DataFrame,
    proposals: pd.DataFrame | None,
    frames: pd.DataFrame,
) -> pd.DataFrame:
    """Join the pair of every row; refuse rows without a pair, proposal or known frame ids."""
    dup = df.duplicated(KEY, keep="first").to_numpy()
    if dup.any():
        r = df.loc[df.index[dup][0]]
        rows.fail(
            dup,
            "repeat a query subimage (same frame, r_session, proposal_method, box_id)",
            f"{r.q_session}/{r.q_camera}/{r.q_utime} -> {r.r_session}, {r.proposal_method} "
            f"box {r.box_id}",
        )
    keys = IMAGE_KEY
    m = df.merge(
        pairs[keys + ["r_camera", "r_utime", "season_pair"]], on=keys, how="left", sort=False
    )
    unpaired = m["r_utime"].isna().to_numpy()
    if unpaired.any():
        i = int(np.flatnonzero(unpaired)[0])
        r = m.iloc[i]
        rows.fail(
            unpaired,
            "match no pair of the run (query frame x reference session)",
            f"{r.q_session}/{r.q_camera}/{r.q_utime} -> {r.r_session}" + _pair_hint(r, pairs),
        )
    m["r_utime"] = m["r_utime"].astype(np.int64)
    if proposals is not None:
        _check_proposals(m, rows, proposals)
    _check_frame_ids(m, rows, frames)
    return m


def _check_proposals(m: pd.DataFrame, rows: Rows, proposals: pd.DataFrame) -> None:
    """Each row's box must be the run's proposal of its (query frame, proposal_method, box_id)."""
    pk = ["session", "camera", "utime", "proposal_method", "box_id"]
    pr = proposals[pk + BOX].rename(
        columns={
            "session": "q_session",
            "camera": "q_camera",
            "utime": "q_utime",
            "x1": "_x1",
            "y1": "_y1",
            "x2": "_x2",
            "y2": "_y2",
        }
    )
    j = m.merge(pr, on=[*QUERY_KEY, "proposal_method", "box_id"], how="left")
    none = j["_x1"].isna().to_numpy()
    if none.any():
        i = int(np.flatnonzero(none)[0])
        known = sorted(set(proposals["proposal_method"]))
        rows.fail(
            none,
            "match no proposal of the run (query frame, proposal_method, box_id)",
            f"proposal_method {j.loc[i, 'proposal_method']!r} box {j.loc[i, 'box_id']}; the run's "
            f"methods: {known}; `harness task export` lists every query subimage",
        )
    off = np.zeros(len(j), bool)
    for a in BOX:
        off |= np.abs(j[a].to_numpy() - j["_" + a].to_numpy()) > BOX_TOLERANCE_PX
    if off.any():
        i = int(np.flatnonzero(off)[0])
        rows.fail(
            off,
            "have a box that is not the run's proposal of that box_id",
            f"({j.loc[i, 'x1']:g}, {j.loc[i, 'y1']:g}, {j.loc[i, 'x2']:g}, {j.loc[i, 'y2']:g})"
            f" vs ({j.loc[i, '_x1']:g}, {j.loc[i, '_y1']:g}, {j.loc[i, '_x2']:g}, "
            f"{j.loc[i, '_y2']:g}) in upright pixels",
        )


def _check_frame_ids(m: pd.DataFrame, rows: Rows, frames: pd.DataFrame) -> None:
    """Each listed reference id must be a frame (utime) of the row's reference session."""
    known_ids = {
        str(s): set(g["utime"].astype(np.int64).tolist())
        for s, g in frames.groupby("session", sort=True)
    }
    bad_ids = []
    example = ""
    for i, (lst, rs) in enumerate(zip(m["ranked"], m["r_session"], strict=True)):
        ids = known_ids.get(str(rs), set())
        stray = [v for v in lst if v not in ids]
        if stray:
            bad_ids.append(i)
            if not example:
                hint = ""
                if ids and stray[0] // 1000 in ids:
                    hint = " (nanoseconds? frame ids are utimes in microseconds)"
                example = f"{stray[0]} is no frame of session {rs}{hint}"
    rows.fail(bad_ids, "list reference ids that are not frames of their reference session", example)


def _pair_hint(r: Any, pairs: pd.DataFrame) -> str:
    """Why a row may match no pair: a unit or a spelling the user can fix."""
    q = pairs[IMAGE_KEY].drop_duplicates()
    if not (q["q_session"] == r.q_session).any():
        return (
            f"; no query frame of session {r.q_session!r}: sessions {sorted(set(q['q_session']))}"
        )
    if not (q["q_camera"] == r.q_camera).any():
        cams = sorted(set(q["q_camera"]))
        return f"; no camera {r.q_camera!r}: cameras {cams} (names are case-sensitive)"
    if (q["q_utime"] == r.q_utime // 1000).any():
        return "; q_utime looks like nanoseconds: utimes are microseconds"
    if not (q["r_session"] == r.r_session).any() or r.r_session == r.q_session:
        return f"; reference sessions of the pairs: {sorted(set(q['r_session']))}"
    return ""


def _check_scores(m: pd.DataFrame, rows: Rows, score_kind: str) -> None:
    """Scores in [0, 1] for similarities, and in the order of ``ranked``."""
    if score_kind == "similarity":
        out_of = [i for i, s in enumerate(m["scores"]) if any(x < 0 or x > 1 for x in s)]
        rows.fail(out_of, "have similarities outside [0, 1] (method §11: d = 1 - s)")
    wrong = [i for i, s in enumerate(m["scores"]) if np.any(np.diff(_distances(s, score_kind)) < 0)]
    other = "similarity" if score_kind == "distance" else "distance"
    rows.fail(
        wrong,
        f"have scores out of the order of 'ranked' (best first means {score_kind}s "
        f"{'rise' if score_kind == 'distance' else 'fall'} along the list; "
        f'if they are {other}s, set [import] score_kind = "{other}")',
    )


def _places(
    m: pd.DataFrame, frames: pd.DataFrame, gt_radius_m: float, max_yaw_deg: float
) -> dict[tuple[str, str], dict[int, np.ndarray]]:
    """(session, camera) -> each reference frame's place P(G), for the references of ``m``."""
    places: dict[tuple[str, str], dict[int, np.ndarray]] = {}
    for (s, c), g in frames.groupby(["session", "camera"], sort=True):
        sel = (m["r_session"] == s) & (m["r_camera"] == c)
        if sel.any():
            places[(str(s), str(c))] = ground_truth_places(
                g, m.loc[sel, "r_utime"].to_numpy(np.int64), gt_radius_m, max_yaw_deg
            )
    return places


def _rank_rows(
    m: pd.DataFrame,
    rank: np.ndarray,
    Lq: np.ndarray,
    dval: np.ndarray,
    exact: np.ndarray,
    psize: np.ndarray,
) -> pd.DataFrame:
    """The rank rows in the built-in engine's columns."""
    cols = [*KEY[:4], "r_camera", "r_utime", "season_pair", "proposal_method", "box_id", *BOX]
    out = m[cols].copy()
    out["rank"] = rank
    out["L"] = Lq
    out["r"] = rank / Lq
    out["r_desc"] = (Lq + 1 - rank) / Lq
    out["d"] = dval
    out["exact"] = exact
    out["place_size"] = psize
    return out


def ranks_from_import(
    df: pd.DataFrame,
    rows: Rows,
    pairs: pd.DataFrame,
    frames: pd.DataFrame,
    proposals: pd.DataFrame | None = None,
    gt_radius_m: float = 0.0,
    max_yaw_deg: float = 45.0,
    score_kind: str = "distance",
) -> tuple[pd.DataFrame, dict[str, int]]:
    """Validate imported lists against the run; compute ``rank, L, r, r', d`` (method §6 and 12).

    Args:
        df: The table :func:`read_import` returned.
        rows: Its row numbering (for messages).
        pairs: The pair table (ground-truth reference frame per query frame and session).
        frames: The frame table (reference ids are checked, places built).
        proposals: Every session's proposals; with them each row must be a proposal of the run,
            and a method's database is the reference frames with a box of that method.
        gt_radius_m: The place's radius, metres (0: the frame G alone).
        max_yaw_deg: The place's heading limit, degrees.
        score_kind: ``distance`` or ``similarity`` (``scores`` only).

    Returns:
        The rank rows (the built-in engine's columns) and counters.

    Raises:
        RetrievalError: Any of method §12's errors, naming the file, the count and an example.
    """
    if score_kind not in SCORE_KINDS:
        raise RetrievalError(f"[import] score_kind = {score_kind!r}; allowed: {SCORE_KINDS}")
    m = _check_against_run(df, rows, pairs, proposals, frames)
    has_scores = "scores" in m.columns
    if has_scores:
        _check_scores(m, rows, score_kind)
    places = _places(m, frames, gt_radius_m, max_yaw_deg)
    db = _databases(proposals)
    n = len(m)
    rank = np.empty(n, np.int64)
    Lq = np.empty(n, np.int64)
    psize = np.empty(n, np.int64)
    dval = np.full(n, np.nan)
    exact = np.ones(n, bool)
    incomplete = []
    counts = {"rows": n, "gt_missing_from_truncated_list": 0}
    cols = ("ranked", "L", "r_utime", "r_session", "r_camera", "proposal_method")
    it = zip(*(m[c] for c in cols), strict=True)
    for i, (lst, L, g, rs, rc, meth) in enumerate(it):
        place = places.get((str(rs), str(rc)), {}).get(int(g), np.array([g], np.int64))
        in_db = db.get((str(rs), str(rc), str(meth)))
        members = set(place.tolist())
        n_place = len(members & in_db) if in_db is not None else len(members)
        psize[i] = max(1, n_place)
        Lq[i] = max(1, int(L) - psize[i] + 1)
        is_member = np.fromiter((v in members for v in lst), bool, len(lst))
        dist = _distances(m["scores"].iloc[i], score_kind) if has_scores else None
        if is_member.any():
            if dist is not None:
                dval[i] = float(dist[is_member].min())
                rank[i] = 1 + int(((dist < dval[i]) & ~is_member).sum())
            else:
                rank[i] = 1 + int((~is_member[: int(np.argmax(is_member))]).sum())
        elif len(lst) >= int(L):
            incomplete.append(i)
        else:
            counts["gt_missing_from_truncated_list"] += 1
            rank[i] = min(int(Lq[i]), len(lst) + 1)
            if dist is not None:
                dval[i] = float(dist[-1])
            exact[i] = False
    rows.fail(incomplete, "have a complete list (len = L) without any frame of the place P(G)")
    rank = np.minimum(rank, Lq)
    out = _rank_rows(m, rank, Lq, dval, exact, psize)
    counts["ranked"] = n
    return out.sort_values(SUBIMAGE_KEY).reset_index(drop=True), counts


def _databases(proposals: pd.DataFrame | None) -> dict[tuple[str, str, str], set[int]]:
    """(session, camera, method) -> the frames that hold a box of the method."""
    if proposals is None or not len(proposals):
        return {}
    g = proposals[["session", "camera", "proposal_method", "utime"]].drop_duplicates()
    return {
        (str(s), str(c), str(meth)): set(x["utime"].astype(np.int64).tolist())
        for (s, c, meth), x in g.groupby(["session", "camera", "proposal_method"], sort=True)
    }


def unranked_images(pairs: pd.DataFrame, ranks: pd.DataFrame) -> pd.DataFrame:
    """The query images (query frame x reference session) of ``pairs`` without any rank row."""
    keys = IMAGE_KEY
    have = ranks[keys].drop_duplicates() if len(ranks) else pd.DataFrame(columns=keys)
    j = pairs[keys].merge(have, on=keys, how="left", indicator=True)
    return j.loc[j["_merge"] == "left_only", keys].reset_index(drop=True)


def write_imported_ranks(
    spec: ImportSpec,
    pairs: pd.DataFrame,
    frames: pd.DataFrame,
    proposals: pd.DataFrame | None,
    radius_m: float,
    max_yaw_deg: float,
    score_kind: str,
    tmp: Path,
) -> dict[str, Any]:
    """Read the user's rank file, score it against the run, write ``tmp/ranks.parquet``.

    Args:
        spec: The localizer's name and rank file.
        pairs: The run's pairs.
        frames: The frame table (the places' frames).
        proposals: Every session's proposals (the rows must be among them).
        radius_m: The place radius, metres.
        max_yaw_deg: The place's heading limit, degrees.
        score_kind: ``distance`` or ``similarity``.
        tmp: The entry's directory.

    Returns:
        The import counters, and whether the file has scores.
    """
    df, rows = read_import(spec.path)
    ranks, counts = ranks_from_import(
        df, rows, pairs, frames, proposals, radius_m, max_yaw_deg, score_kind
    )
    write_parquet(tmp / "ranks.parquet", ranks)
    return {**counts, "has_scores": int("scores" in df.columns)}

"""The no-change null: pairs that hold no change by construction, scored by the same detector.

docs/decisions.md, *Calibrated alarms*. A frame's calibrated score is the share of null frames that
score at least as high (:func:`harness.detect.calibrate.exceedance`); a box's, the share of the
null frames' change boxes. The null is drawn from the map alone, never from the new session:

- ``neighbours``: each drawn map frame against the next frame of the map's own sequence (the
  same camera, the next time), and that frame against it: a static scene seen twice a moment
  apart;
- ``perturbed``: each drawn map frame against a perturbed copy of itself (:mod:`harness.perturb`),
  within ``[detect.null]``'s limits: where the map is no sequence (pairs by name or retrieval).

Both are scored by the run's paired-frame localizer (``keypoints`` or ``local``) and the same
chunks, fusion, prior and NMS as the query frames, cached like them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from harness.detect.config import NullConfig
from harness.imagestore import ImageRef
from harness.pairs.modes import PAIRING_MODES, kind_of
from harness.pairs.table import PAIR_COLUMNS
from harness.perturb import Perturbation, fragment
from harness.records import FRAME_KEY
from harness.runtime.cache import read_cached_parquet, stable_hash
from harness.runtime.stage import Table

log = logging.getLogger(__name__)

#: The camera name of a perturbed copy, and of a null query: the original's, then this, then the
#: null pair's number.
COPY, QUERY = "~null", "~q"


@dataclass(frozen=True)
class NullChoice:
    """The map frames the null pairs query, and each pair's reference, before any proposal.

    One row per pair in both (rows of the frame table); a ``perturbed`` pair's reference is its
    query frame, perturbed when the pairs are made (:func:`null_pairs`).
    """

    queries: pd.DataFrame
    references: pd.DataFrame
    construction: str
    copies: int  # perturbed copies of each drawn map frame (0: neighbours)

    def query_frames(self, frames: pd.DataFrame) -> pd.DataFrame:
        """The rows of ``frames`` that the pairs query, in its order: the map frames proposed."""
        asked = pd.MultiIndex.from_frame(self.queries[FRAME_KEY])
        return frames[pd.MultiIndex.from_frame(frames[FRAME_KEY]).isin(asked)]


@dataclass(frozen=True)
class NullPairs:
    """The null's frames (the run's, with any perturbed copies), pairs and construction."""

    frames: Table
    pairs: Table
    proposals: Table  # the null queries' proposals: their frames' own
    construction: str
    copies: int  # perturbed copies of each drawn map frame (0: neighbours)
    no_proposals: int = 0  # pairs left out: their query frame has no proposal


def construction_for(nc: NullConfig, by: str) -> str:
    """``neighbours`` or ``perturbed``: ``auto`` by the pairing mode ``by`` (``[pairs] by``).

    A map paired by pose, by order or by sequence is a sequence; by name or retrieval it is not.
    """
    if nc.construction != "auto":
        return nc.construction
    unordered = by == "name" or (kind_of(by) == "retrieval" and not PAIRING_MODES[by].sequence)
    return "perturbed" if unordered else "neighbours"


def draw(nc: NullConfig, i: int, moves: np.ndarray | None = None) -> Perturbation:
    """The ``i``-th perturbed copy's values (``nc.seed``, ``i``).

    Gain, offset, blur and JPEG quality uniform within the limits; the shift, rotation and scale
    likewise, or, given ``moves`` ((n, 5): the run's registrations as shift x, shift y, rotation,
    scale and the residual the homography leaves), one of them drawn uniformly, its residual as
    the copy's smooth displacement (``wobble``): the null moves as the run's pairs do, parallax
    included.
    """
    rng = np.random.default_rng([nc.seed, i])
    u = rng.uniform(-1.0, 1.0, 7)
    q = int(rng.integers(nc.jpeg_quality, 96)) if nc.jpeg_quality else 0
    dx, dy, rot, sc = (
        nc.shift * u[2],
        nc.shift * u[3],
        nc.rotation_deg * u[4],
        1.0 + nc.scale * u[5],
    )
    wobble = 0.0
    if moves is not None and len(moves):
        dx, dy, rot, sc, wobble = moves[int(rng.integers(len(moves)))]
    return Perturbation(
        gain=round(1.0 + nc.gain * u[0], 4),
        offset=round(nc.offset * u[1], 3),
        dx=round(float(dx), 5),
        dy=round(float(dy), 5),
        rotation_deg=round(float(rot), 4),
        scale=round(float(sc), 5),
        blur=round(nc.blur * abs(u[6]), 6),
        jpeg=q,
        wobble=round(float(wobble), 6) if np.isfinite(wobble) else 0.0,
    )


def _evenly(n: int, k: int) -> np.ndarray:
    """``min(n, k)`` indices of ``range(n)`` spread evenly, first and last kept."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(np.int64))


def null_choice(frames: Table, map_session: str, nc: NullConfig, by: str) -> NullChoice:
    """The null pairs' map frames, chosen from the map's frames alone (``[pairs] by``: ``by``).

    ``neighbours``: the pairs (i, i + 1), (i + 1, i) of consecutive frames of one camera, ``pairs``
    of them spread evenly; ``perturbed``: each map frame in turn, as many times as ``pairs`` needs.
    Only these frames of the map are then proposed: no localizer of such a run reads the others.
    """
    how = construction_for(nc, by)
    fr = frames.df
    mine = fr[(fr["session"] == map_session)].sort_values(["camera", "utime"], kind="stable")
    mine = mine.reset_index(drop=True)
    copies = 0
    if how == "neighbours":
        cam = mine["camera"].to_numpy()
        i = np.flatnonzero(cam[:-1] == cam[1:])
        both = np.stack([np.c_[i, i + 1], np.c_[i + 1, i]], axis=1).reshape(-1, 2)
        both = both[_evenly(len(both), nc.pairs)]
        q = mine.iloc[both[:, 0]].reset_index(drop=True)
        r = mine.iloc[both[:, 1]].reset_index(drop=True)
    else:
        copies = max(1, math.ceil(nc.pairs / max(len(mine), 1)))
        order = np.arange(min(nc.pairs, len(mine) * copies))
        q = mine.iloc[order % max(len(mine), 1)].reset_index(drop=True)
        r = q.copy()
    return NullChoice(q, r, how, copies)


def null_pairs(
    frames: Table,
    choice: NullChoice,
    proposed: Table,
    nc: NullConfig,
    moves: np.ndarray | None = None,
) -> NullPairs:
    """The null pairs of ``choice`` whose query frame has proposals (``proposed``: the map's).

    The query side of null pair ``j`` is a map frame under a name of its own (camera
    ``<camera>~q<j>``: a frame may be the query of several null pairs) with the frame's image and
    proposals; the reference, its neighbour in the map's order or a perturbed copy of it (camera
    ``<camera>~null<j>``, its image URI naming the copy's drawn values). A pair whose query frame
    has no proposal is left out and counted (``no_proposals``).
    """
    how = choice.construction
    have = pd.MultiIndex.from_frame(proposed.df[FRAME_KEY].drop_duplicates())
    keep = pd.MultiIndex.from_frame(choice.queries[FRAME_KEY]).isin(have)
    q = choice.queries[keep].reset_index(drop=True)
    r = choice.references[keep].reset_index(drop=True)
    if how == "perturbed":
        r["camera"] = [f"{c}{COPY}{j}" for j, c in enumerate(q["camera"])]
        r["image"] = [f"{img}{fragment(draw(nc, j, moves))}" for j, img in enumerate(q["image"])]
    own = q.copy()
    own["camera"] = [f"{c}{QUERY}{j}" for j, c in enumerate(q["camera"])]
    pairs = pd.DataFrame(
        {
            "q_session": own["session"].astype(str).to_numpy(),
            "q_camera": own["camera"].astype(str).to_numpy(),
            "q_utime": own["utime"].astype(np.int64).to_numpy(),
            "r_session": r["session"].astype(str).to_numpy(),
            "r_camera": r["camera"].astype(str).to_numpy(),
            "r_utime": r["utime"].astype(np.int64).to_numpy(),
            "distance_m": 0.0,
            "yaw_diff_deg": 0.0,
            "season_pair": "null",
        },
        columns=PAIR_COLUMNS,
    )
    named = pd.DataFrame({
        "session": q["session"].to_numpy(), "camera": q["camera"].to_numpy(),
        "utime": q["utime"].to_numpy(), "null_camera": own["camera"].to_numpy(),
    })  # fmt: skip
    props = proposed.df.merge(named, on=FRAME_KEY, sort=False)
    props = props.assign(camera=props.pop("null_camera"))
    rows = pairs[PAIR_COLUMNS[:6]].itertuples(index=False, name=None)
    marks = [ImageRef.parse(u).perturbation or "" for u in r["image"]] if how == "perturbed" else []
    # the map's (its proposals' key holds its ingest) and the drawn copies' values: a run whose
    # copies move as another's did scores no null pair again
    key = stable_hash("detect-null", proposed.key, how, dataclasses.asdict(nc), list(rows), marks)
    extra = [own, r] if how == "perturbed" else [own]
    return NullPairs(
        Table(pd.concat([frames.df, *extra], ignore_index=True), stable_hash("null-frames", key)),
        Table(pairs, key),
        Table(props, stable_hash("null-proposals", key)),
        how,
        choice.copies,
        int((~keep).sum()),
    )


@dataclass(frozen=True)
class NullScores:
    """The null's frame scores and change-box scores, and what ``detect.json`` says of it."""

    frames: np.ndarray
    boxes: np.ndarray
    record: dict[str, Any]
    entries: tuple[str, ...] = ()  # the null's detect chunks (cache/detect-null/<key>)


def run_moves(entries: list[Any]) -> np.ndarray | None:
    """The run's registrations as (shift x, shift y, rotation, scale, residual) rows.

    From its chunks' frame rows; None where none registered.
    """
    cols = ["reg_dx", "reg_dy", "reg_rotation_deg", "reg_scale", "reg_residual"]
    parts = [read_cached_parquet(e.path / "frames.parquet") for e in entries]
    fr = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
    if not set(cols) <= set(fr.columns):
        return None
    m = fr[cols].to_numpy(np.float64)
    m = m[np.isfinite(m).all(axis=1)]
    return m if len(m) else None


def null_record(
    nc: NullConfig,
    null: NullPairs,
    scored: np.ndarray,
    boxes: int,
    moves: np.ndarray | None = None,
) -> dict:
    """``detect.json``'s ``calibration``: the null's construction, size, limits and moves."""
    rec: dict[str, Any] = {
        "method": "null",
        "construction": null.construction,
        "pairs": len(null.pairs.df),
        **({"left_out_no_proposals": null.no_proposals} if null.no_proposals else {}),
        "frames_scored": int(np.isfinite(scored).sum()),
        "boxes": int(boxes),
    }
    if null.construction == "perturbed":
        rec["copies_per_map_frame"] = null.copies
        rec["limits"] = {
            k: v for k, v in dataclasses.asdict(nc).items() if k not in ("construction", "pairs")
        }
        if moves is not None and len(moves):
            rec["moves"] = {
                "drawn_from": f"the {len(moves)} registered pairs of this run",
                "largest_shift": round(float(np.abs(moves[:, :2]).max()), 4),
                "largest_rotation_deg": round(float(np.abs(moves[:, 2]).max()), 3),
                "scale_range": [round(float(moves[:, 3].min()), 4),
                                round(float(moves[:, 3].max()), 4)],
                "median_residual": round(float(np.median(moves[:, 4])), 5),
            }  # fmt: skip
        else:
            rec["moves"] = {"drawn_from": "the limits (no pair of this run was registered)"
                            if nc.moves == "run" else "the limits"}  # fmt: skip
    return rec

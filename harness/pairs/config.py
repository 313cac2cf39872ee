"""The pairs stage's config: ``[pairs]`` (method §4 and 13.2) and its checks."""

from __future__ import annotations

from dataclasses import dataclass

from harness.checks import check_value
from harness.pairs.modes import PAIRING_MODES

#: ``[pairs] by``: how a query frame finds its map frame (method §4 and 13.2).


@dataclass(frozen=True)
class PairsConfig:
    """``[pairs]``: cross-season pairing (method §4; degrees, metres)."""

    # a pair's largest heading difference, degrees (the paper's 45)
    max_yaw_diff_deg: float = 45.0
    # a pair's largest distance between the two frames, metres
    max_distance_m: float | None = 10.0
    # query frames at least this far apart, metres (0: every frame)
    stride_m: float = 0.0
    queries: str = "annotated"  # "annotated": only annotated query frames; "all": every frame
    # "pose": the nearest viewpoint by pose (method §4); sessions without poses (method §13.2):
    # "name": the map image of the same file name (stem); "order": the i-th image of each session
    # in file-name order; "retrieval": the map frame the query's subimages retrieve best with the
    # run's localizer; "sequence": the same retrieval scored over runs of consecutive frames
    # (SeqSLAM), for two traverses of one route
    by: str = "pose"
    # by other than "pose": the ground-truth place is the paired frame and this many neighbours
    # on each side in the map's order (method §13.2)
    place_frames: int = 2
    # a pair whose pair_confidence is below this is an "uncertain pair": flagged in frames.csv,
    # left out of detect's most-changed list and marked on the page (method §13.2)
    min_pair_confidence: float = 0.05
    # by = "sequence": the query frames of one sequence window (centred on the frame)
    sequence_frames: int = 11
    # by = "sequence" or "retrieval": a frame whose grey levels' standard deviation (0-255) is
    # below this carries no place (dark, blank, a lens cap, a tunnel): never a map frame's
    # candidate, and a query frame with none gets no pair (docs/method.md; 0: every frame)
    min_place_contrast: float = 10.0


def check_pairs(pa: PairsConfig, where: str) -> None:
    """``[pairs]``: the heading gate, distances, which queries."""
    c = check_value
    c(
        0 < pa.max_yaw_diff_deg <= 180,
        where,
        "[pairs] max_yaw_diff_deg",
        pa.max_yaw_diff_deg,
        "(0, 180]",
    )
    c(
        pa.max_distance_m is None or pa.max_distance_m > 0,
        where,
        "[pairs] max_distance_m",
        pa.max_distance_m,
        "> 0 metres",
    )
    c(pa.stride_m >= 0, where, "[pairs] stride_m", pa.stride_m, ">= 0 metres")
    c(
        pa.queries in ("annotated", "all"),
        where,
        "[pairs] queries",
        pa.queries,
        "'annotated' or 'all'",
    )
    c(
        pa.by in PAIRING_MODES,
        where,
        "[pairs] by",
        pa.by,
        " or ".join(repr(m) for m in PAIRING_MODES),
    )
    c(pa.place_frames >= 0, where, "[pairs] place_frames", pa.place_frames, ">= 0 frames")
    c(pa.sequence_frames >= 1, where, "[pairs] sequence_frames", pa.sequence_frames, ">= 1")
    c(0 <= pa.min_place_contrast < 128, where, "[pairs] min_place_contrast",
      pa.min_place_contrast, "[0, 128) grey levels (0: every frame carries a place)")  # fmt: skip
    c(
        0 <= pa.min_pair_confidence <= 1,
        where,
        "[pairs] min_pair_confidence",
        pa.min_pair_confidence,
        "in [0, 1]",
    )

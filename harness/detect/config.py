"""``harness detect``'s config: ``[detect]`` (method §13.1 and 13.3) and its checks."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from harness.checks import check_value
from harness.localizers.config import (
    KeypointConfig,
    LocalConfig,
    LocalizerConfig,
    check_keypoints,
    check_local,
)
from harness.methods import (
    BOX_GENERATORS,
    BOX_PRIORS,
    BOX_SCORES,
    CALIBRATIONS,
    DETECT_LOCALIZERS,
    known_proposal_methods,
    rules_where,
)

#: The proposal method ``harness detect``'s local localizer ranks: the frame's colour regions,
#: which meet most change objects (docs/method.md, *Detect*).
LOCAL_PROPOSALS = "segments"


#: ``[detect.null] construction``: map frames against their neighbours in the map's sequence,
#: against perturbed copies of themselves, or by the map: neighbours where it is a sequence.
NULL_CONSTRUCTIONS = ("auto", "neighbours", "perturbed")


@dataclass(frozen=True)
class NullConfig:
    """``[detect.null]``: the pairs that hold no change by construction, scored by the detector.

    docs/method.md, *Calibrated alarms*. Every limit is the largest draw either way; sizes are
    shares of the frame.
    """

    # "neighbours": each drawn map frame against the next one of the map's own sequence and back (a
    # static scene seen twice a moment apart); "perturbed": against a perturbed copy of itself;
    # "auto": neighbours where the map is a sequence (pairs by pose, order or sequence), else
    # perturbed (pairs by name or retrieval)
    construction: str = "auto"
    # the null pairs, drawn evenly over the map (perturbed: as many copies of each map frame as
    # that takes); at a rate a, a frame can be flagged only with at least 1/a - 1 of them
    pairs: int = 100
    # the draws of the perturbed copies
    seed: int = 0
    # perturbed copies: gain in [1 - gain, 1 + gain], offset in [-offset, offset] grey levels
    gain: float = 0.1
    offset: float = 8.0
    # a shift of up to this share of the frame each way, a rotation of up to rotation_deg, a
    # scale within [1 - scale, 1 + scale]
    shift: float = 0.02
    rotation_deg: float = 2.0
    scale: float = 0.03
    # a Gaussian blur of sigma up to this share of the longer side (0.002: 1.3 px at 640)
    blur: float = 0.002
    # re-encoded as JPEG at a quality drawn in [jpeg_quality, 95] (0: never re-encoded)
    jpeg_quality: int = 70


def check_null(nc: NullConfig, where: str) -> None:
    """``[detect.null]``'s values (one ``ERROR:`` line naming the key)."""
    c = check_value
    c(nc.construction in NULL_CONSTRUCTIONS, where, "construction", nc.construction,
      ", ".join(NULL_CONSTRUCTIONS))  # fmt: skip
    c(nc.pairs >= 1, where, "pairs", nc.pairs, ">= 1 (100 flags at 0.01)")
    c(0 <= nc.gain < 1, where, "gain", nc.gain, "[0, 1)")
    c(0 <= nc.offset <= 64, where, "offset", nc.offset, "[0, 64] grey levels")
    c(0 <= nc.shift <= 0.2, where, "shift", nc.shift, "[0, 0.2] of the frame")
    c(0 <= nc.rotation_deg <= 20, where, "rotation_deg", nc.rotation_deg, "[0, 20] degrees")
    c(0 <= nc.scale < 0.5, where, "scale", nc.scale, "[0, 0.5)")
    c(0 <= nc.blur <= 0.05, where, "blur", nc.blur, "[0, 0.05] of the longer side")
    c(nc.jpeg_quality == 0 or 10 <= nc.jpeg_quality <= 95, where, "jpeg_quality",
      nc.jpeg_quality, "0 (none) or 10-95")  # fmt: skip


@dataclass(frozen=True)
class DetectConfig:
    """``[detect]``: how ``harness detect`` turns LoC into change boxes (method §13.1).

    The one options record of ``harness detect``: its flags, as typed, replace these fields for a
    run (``harness.cli.runs.detect_options``), and the run reads nothing else.
    """

    # the fusion rule whose LoC scores the boxes (one with detect = true; --fusion)
    fusion: str = "rank_fusion"
    # the boxes' NMS: the IoU above which the lower-scored box goes, and the boxes kept per frame
    nms_iou: float = 0.5
    # change boxes kept per frame, at most
    max_boxes: int = 10
    # query frames per cached unit (the unit a killed run resumes at)
    chunk_frames: int = 64
    # the most changed places shown on the map and the page (--top)
    top: int = 10

    # the box generator: "subimages" (the ranked subimages, each scored by its own r: with the
    # local localizer, the frame's colour regions, method §13.3), "fused" (the fused qBBs, §13),
    # "locmap" (connected regions of the
    # thresholded LoC map), "proposals" (the original proposals scored by the LoC inside) or
    # "segments" (the frame's colour regions, [proposals.segments], scored by the LoC inside)
    boxes: str = "subimages"
    # locmap / proposals / segments: a box's score from the LoC map, "max" or "mean" inside it,
    # or "contrast" (the mean inside less the mean of the ring around it, half the box wide)
    box_score: str = "max"
    # locmap: the level, as a share of the frame's LoC range (lo + level * (hi - lo))
    locmap_level: float = 0.5
    # the narrowest change box, pixels a side: thinner candidates (slivers where fused qBBs
    # barely overlap) are dropped before NMS and counted (detect.json: thin_boxes_dropped)
    min_box_side: float = 2.0
    # the nominal false-alarm rate: boxes and frames whose calibrated score (exceedance) is at
    # most this are alarms (alarms.csv; harness detect --alarm overrides it)
    alarm: float = 0.01
    # what the calibrated scores are measured against: "null" (pairs that hold no change by
    # construction, [detect.null], scored by the same detector) or "within-run" (the run's own
    # frames and candidate boxes: it can never say that nothing changed)
    calibration: str = "null"
    # the no-change null's construction and size
    null: NullConfig = field(default_factory=NullConfig)
    # what ranks the subimages: "keypoints" (each subimage's share of keypoints that do not
    # localize in its paired map frame, with [detect.keypoints]: chosen by docs/method.md's rule,
    # *Keypoint localization*), "local" (each subimage ranked inside its paired map frame by NCC,
    # with [detect.local]) or "config" (the config's localizers: the paper's detector)
    localizer: str = "keypoints"
    # a prior a box's score is fused with: "area" (the mean of the box's percentile among its
    # frame's candidates by score and by area, method §13.3: docs/method.md measures it) or "none"
    box_prior: str = "area"
    # the local localizer's options (harness.localizers.local.LocalConfig)
    local: LocalConfig = field(default_factory=LocalConfig)
    # the proposal method whose boxes the local or keypoints localizer ranks: "segments" (the
    # frame's colour regions) or "selective" (Selective Search, [proposals.selective]), or any
    # proposal method
    proposals: str = LOCAL_PROPOSALS
    # keypoint localization's options (localizer = "keypoints"; harness.localizers.keypoints)
    keypoints: KeypointConfig = field(default_factory=KeypointConfig)

    def record(self, seed: int, segments: Any) -> dict[str, Any]:
        """What ``detect.json`` and the chunks' cache keys hold of a run's options.

        ``seed`` (``[fusion] seed``) draws the random baseline; ``segments``
        (``[proposals.segments]``) is there where the boxes or the local localizer read the colour
        regions; ``local`` and ``localizer`` only with the local localizer (the paper's detector:
        its record as before); ``alarm`` is not (the alarms are drawn after the chunks).
        """
        mine = dataclasses.asdict(self)
        out: dict[str, Any] = {k: mine[k] for k in ("fusion", "nms_iou", "max_boxes")}
        out |= {"chunk_frames": self.chunk_frames, "top": self.top, "seed": seed}
        out |= {k: mine[k] for k in ("boxes", "box_score", "locmap_level", "min_box_side")}
        if self.boxes == "segments" or self.localizer in ("local", "keypoints"):
            out["segments"] = dataclasses.asdict(segments)
        out |= {"localizer": self.localizer, "box_prior": self.box_prior, "local": mine["local"]}
        if self.localizer == "keypoints":  # its options in place of the local localizer's
            del out["local"]
            out["keypoints"] = mine["keypoints"]
        elif self.localizer != "local":
            del out["local"], out["localizer"]
        if self.proposals != LOCAL_PROPOSALS:
            out["proposals"] = self.proposals
        return out

    def local_localizer(self) -> LocalizerConfig | None:
        """What ``localizer = "local"`` or ``"keypoints"`` measures (None: the config's)."""
        if self.localizer == "keypoints":
            return LocalizerConfig("keypoints", "keypoints", (self.proposals,), self.keypoints)
        if self.localizer != "local":
            return None
        return LocalizerConfig("local", "local", (self.proposals,), self.local)


def check_detect(dt: DetectConfig, where: str) -> None:
    """``[detect]`` (method §13.1)."""
    c = check_value
    detect_rules = rules_where(detect=True)
    c(dt.fusion in detect_rules, where, "[detect] fusion", dt.fusion, ", ".join(detect_rules))
    c(0 < dt.nms_iou <= 1, where, "[detect] nms_iou", dt.nms_iou, "(0, 1]")
    c(dt.max_boxes >= 1, where, "[detect] max_boxes", dt.max_boxes, ">= 1 per frame")
    c(dt.chunk_frames >= 1, where, "[detect] chunk_frames", dt.chunk_frames, ">= 1")
    c(dt.top >= 0, where, "[detect] top", dt.top, ">= 0 places")
    c(
        dt.boxes in BOX_GENERATORS,
        where,
        "[detect] boxes",
        dt.boxes,
        f"one of {', '.join(BOX_GENERATORS)} (method §13.1)",
    )
    c(
        dt.box_score in BOX_SCORES,
        where,
        "[detect] box_score",
        dt.box_score,
        f"one of {', '.join(BOX_SCORES)}",
    )
    c(0 < dt.alarm < 1, where, "[detect] alarm", dt.alarm, "(0, 1): a false-alarm rate")
    c(
        dt.localizer in DETECT_LOCALIZERS,
        where,
        "[detect] localizer",
        dt.localizer,
        " or ".join(DETECT_LOCALIZERS),
    )
    c(dt.calibration in CALIBRATIONS, where, "[detect] calibration", dt.calibration,
      " or ".join(CALIBRATIONS))  # fmt: skip
    check_null(dt.null, f"{where} [detect.null]")
    check_local(dt.local, f"{where} [detect.local]")
    check_keypoints(dt.keypoints, f"{where} [detect.keypoints]")
    c(
        dt.proposals in known_proposal_methods(),
        where,
        "[detect] proposals",
        dt.proposals,
        ", ".join(known_proposal_methods()),
    )
    c(
        dt.box_prior in BOX_PRIORS,
        where,
        "[detect] box_prior",
        dt.box_prior,
        " or ".join(BOX_PRIORS),
    )
    c(
        0 < dt.locmap_level < 1,
        where,
        "[detect] locmap_level",
        dt.locmap_level,
        "(0, 1): a share of each frame's LoC range",
    )
    c(
        0 <= dt.min_box_side < 1e4,
        where,
        "[detect] min_box_side",
        dt.min_box_side,
        "pixels a side, >= 0 (0: keep every box)",
    )

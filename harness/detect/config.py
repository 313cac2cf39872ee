"""``harness detect``'s config: ``[detect]`` (method §13.1 and 13.3) and its checks."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
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
from harness.localizers.kinds import LOCALIZER_KINDS, paired_kinds
from harness.methods import known_proposal_methods, rules_where

#: ``harness detect``'s box generators (method §13.1, ``[detect] boxes``), the default first.
BOX_GENERATORS = ("fused", "locmap", "proposals", "segments", "subimages")
#: What a candidate box's score is fused with (``[detect] box_prior``, method §13.3): its area, or
#: nothing (the score alone, as the paper's detector).
BOX_PRIORS = ("area", "difference", "difference_product", "none")
#: How a generator scores a candidate box from the LoC map (``[detect] box_score``).
BOX_SCORES = ("max", "mean", "contrast")
#: ``[detect] calibration``: the no-change null (docs/decisions.md, *Calibrated alarms*) or the
#: run's own scores (the share of the run's frames and candidate boxes that score as high).
CALIBRATIONS = ("null", "within-run")

#: ``[detect] localizer``'s value for the config's own localizers (the paper's detector); every
#: other value is a localizer kind that ranks inside the paired map frame.
CONFIG_LOCALIZERS = "config"


def detect_localizers() -> tuple[str, ...]:
    """What ``[detect] localizer`` may name: each paired-frame kind, then ``config``."""
    return (*paired_kinds(), CONFIG_LOCALIZERS)


#: The proposal method ``harness detect``'s local localizer ranks: the frame's colour regions,
#: which meet most change objects (docs/decisions.md, *Detect*).
LOCAL_PROPOSALS = "segments"


#: ``[detect.null] construction``: map frames against their neighbours in the map's sequence,
#: against perturbed copies of themselves, or by the map: neighbours where it is a sequence.
NULL_CONSTRUCTIONS = ("auto", "neighbours", "perturbed")


@dataclass(frozen=True)
class DifferenceConfig:
    """``[detect.difference]``: registration and the plain difference (docs/method.md).

    Every length is a share of the frame's diagonal.
    """

    # the recipe: "reference" (RootSIFT and MAGSAC registration, a colour distance in CIELAB
    # with a shift tolerance, the colours' novelty where a pair cannot be registered, every box of
    # Selective Search scored by its contrast with a ring, registered pairs ranked first: the
    # method's words, checked pair by pair against a reference run; harness.detect.plain) or
    # "novelty-product" (the registration of [detect.keypoints], the difference times the
    # colours' novelty, the settings below). The reference recipe reads min_inliers,
    # register_side and side alone of the settings below
    recipe: str = "reference"
    # a pair is comparable with at least this many homography inliers ...
    min_inliers: int = 15
    # ... a warped map that covers at least this share of the query frame ...
    min_footprint: float = 0.5
    # ... and a warp whose local scale stays within [1 / max_scale, max_scale]
    max_scale: float = 3.0
    # the registration's frames: longer side at most this (pixels)
    register_side: int = 640
    # a fallback's affine fit of the intensities (not_comparable = "fallback"): its frames'
    # longer side (pixels)
    fallback_side: int = 160
    # the difference's frames: longer side at most this (pixels)
    side: int = 640
    # each query pixel's smallest colour distance over shifts up to this (2 px at 640 x 480)
    shift: float = 0.0025
    # the difference map's Gaussian blur, sigma (4 px at 640 x 480)
    blur: float = 0.005
    # a box's score: "contrast" (its mean difference less its ring's) or "ratio" (its mean
    # difference over its ring's, plus one colour unit): a change differs more than its surroundings
    box_score: str = "ratio"
    # the ring around a box: the box grown by this share of its width and height on each side
    ring: float = 0.25
    # the difference times the colours' novelty: "novelty" (how much likelier each new pixel's
    # colour is in the new frame than anywhere in its map frame, scored like the difference; no
    # registration needed) or "none" (the difference alone)
    colour: str = "novelty"
    # the novelty's colour histogram: bins of CIELAB's L, a and b
    colour_bins: tuple[int, int, int] = (8, 16, 16)
    # the novelty's frames: longer side at most this (pixels)
    colour_side: int = 320


def check_difference(dc: DifferenceConfig, where: str) -> None:
    """``[detect.difference]``'s values (one ``ERROR:`` line naming the key)."""
    c = check_value
    c(dc.recipe in DIFFERENCE_RECIPES, where, "recipe", dc.recipe, " or ".join(DIFFERENCE_RECIPES))
    c(dc.min_inliers >= 4, where, "min_inliers", dc.min_inliers, ">= 4 (a homography's four)")
    c(0 <= dc.min_footprint <= 1, where, "min_footprint", dc.min_footprint, "[0, 1]")
    c(dc.max_scale > 1, where, "max_scale", dc.max_scale, "> 1")
    c(dc.register_side >= 64, where, "register_side", dc.register_side, ">= 64 pixels")
    c(dc.fallback_side >= 32, where, "fallback_side", dc.fallback_side, ">= 32 pixels")
    c(dc.side >= 32, where, "side", dc.side, ">= 32 pixels")
    c(0 <= dc.shift <= 0.05, where, "shift", dc.shift, "[0, 0.05] of the diagonal")
    c(0 <= dc.blur <= 0.05, where, "blur", dc.blur, "[0, 0.05] of the diagonal")
    c(dc.box_score in DIFFERENCE_SCORES, where, "box_score", dc.box_score,
      " or ".join(DIFFERENCE_SCORES))  # fmt: skip
    c(0 < dc.ring <= 2, where, "ring", dc.ring, "(0, 2]: a share of the box each side")
    c(dc.colour in COLOUR_SCORES, where, "colour", dc.colour, " or ".join(COLOUR_SCORES))
    c(len(dc.colour_bins) == 3 and all(2 <= b <= 64 for b in dc.colour_bins), where,
      "colour_bins", dc.colour_bins, "three bin counts (L, a, b), each in [2, 64]")  # fmt: skip
    c(dc.colour_side >= 16, where, "colour_side", dc.colour_side, ">= 16 pixels")


#: ``[detect.difference] recipe``'s values.
DIFFERENCE_RECIPES = ("reference", "novelty-product")
#: ``[detect.difference] box_score``'s values.
DIFFERENCE_SCORES = ("contrast", "ratio")
#: ``[detect.difference] colour``'s values.
COLOUR_SCORES = ("novelty", "none")


#: ``[detect] not_comparable`` and ``[detect] bootstrap_group``'s values.
NOT_COMPARABLE = ("drop", "fallback", "keep")
BOOTSTRAP_GROUPS = ("map_image", "frame")


@dataclass(frozen=True)
class NullConfig:
    """``[detect.null]``: the pairs that hold no change by construction, scored by the detector.

    docs/decisions.md, *Calibrated alarms*. Every limit is the largest draw either way; sizes are
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
    # perturbed copies' shift, rotation and scale: "run" (each drawn from the registrations of the
    # run's own pairs, so the null moves as they do; the limits above where none registered) or
    # "limits" (uniform within the limits above)
    moves: str = "run"


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
    c(nc.moves in ("run", "limits"), where, "moves", nc.moves, "run or limits")


@dataclass(frozen=True)
class DetectConfig:
    """``[detect]``: how ``harness detect`` turns LoC into change boxes (method §13.1).

    The one options record of ``harness detect``: its flags, as typed, replace these fields for a
    run (``harness.config.assemble.with_overrides``), and the run reads nothing else.
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
    # localize in its paired map frame, with [detect.keypoints]: chosen by docs/decisions.md's rule,
    # *Choosing the default*), "local" (each subimage ranked inside its paired map frame by NCC,
    # with [detect.local]) or "config" (the config's localizers: the paper's detector)
    localizer: str = "keypoints"
    # what a box's score is fused with: "difference_product" (the plain difference of the
    # registered pair, [detect.difference], floored at 0, times the score: the default, chosen by
    # docs/decisions.md's rule), "difference" (the mean of the two within-frame percentiles), "area"
    # (the mean of the box's percentiles by score and by area, method §13.3) or "none"
    box_prior: str = "difference_product"
    # difference_product: the power of the localizer's score in the product (difference x
    # score ^ weight): 1 weighs the two alike in log terms; 4, the default (chosen by
    # docs/decisions.md's rule), lets localization reorder the boxes the difference scores alike
    localization_weight: float = 4.0
    # the local localizer's options (harness.localizers.local.LocalConfig)
    local: LocalConfig = field(default_factory=LocalConfig)
    # the proposal method whose boxes the local or keypoints localizer ranks: "selective"
    # (Selective Search, [proposals.selective]: the plain difference's own boxes too), "segments"
    # (the frame's colour regions) or any proposal method
    proposals: str = "selective"
    # keypoint localization's options (localizer = "keypoints"; harness.localizers.keypoints);
    # its features and ratio test also register each pair for the plain difference
    keypoints: KeypointConfig = field(default_factory=KeypointConfig)
    # each pair's registration and plain difference (harness.detect.difference)
    difference: DifferenceConfig = field(default_factory=DifferenceConfig)
    # a pair that cannot be registered is not comparable (no alarm, never among the most
    # changed): "drop" (no box and no score; its annotated changes stay in Table D as misses),
    # "fallback" (compared as it stands, without a warp: its boxes are kept, marked in
    # frames.csv's comparable column and measured apart in Table D) or "keep" (the detector's
    # boxes stay, marked likewise, with no difference read)
    not_comparable: str = "fallback"
    # the query frames registered, compared and fused side by side (0: one per core); the same
    # bytes whatever the count, so in no cache key
    threads: int = 0
    # Table D's intervals resample groups of annotated frames: "map_image" (frames whose map
    # images hold the same bytes, or the same map frame, are one group: pairs that share a view
    # are not independent) or "frame" (each annotated frame alone)
    bootstrap_group: str = "map_image"

    def record(self, seed: int, segments: Any, selective: Any = None) -> dict[str, Any]:
        """What ``detect.json`` and the chunks' cache keys hold of a run's options.

        ``seed`` (``[fusion] seed``) draws the random baseline; ``segments``
        (``[proposals.segments]``) is there where the boxes or the local localizer read the colour
        regions; ``local`` and ``localizer`` only with the local localizer (the paper's detector's
        record has neither); ``alarm`` is not (the alarms are drawn after the chunks).
        """
        mine = dataclasses.asdict(self)
        out: dict[str, Any] = {k: mine[k] for k in ("fusion", "nms_iou", "max_boxes")}
        out |= {"chunk_frames": self.chunk_frames, "top": self.top, "seed": seed}
        out |= {k: mine[k] for k in ("boxes", "box_score", "locmap_level", "min_box_side")}
        if self.boxes == "segments" or self.localizer != CONFIG_LOCALIZERS:
            out["segments"] = dataclasses.asdict(segments)
        out |= {"localizer": self.localizer, "box_prior": self.box_prior, "local": mine["local"]}
        if self.box_prior == "difference_product":
            out["localization_weight"] = self.localization_weight
        if self.localizer == CONFIG_LOCALIZERS:
            del out["local"], out["localizer"]
        elif self.localizer != "local":  # its options in place of the local localizer's
            del out["local"]
            out[self.localizer] = dataclasses.asdict(self.paired_options())
        if self.proposals != LOCAL_PROPOSALS:
            out["proposals"] = self.proposals
        out["difference"] = mine["difference"]
        out["keypoints"] = mine["keypoints"]  # the pairs read are registered
        out["not_comparable"] = self.not_comparable
        if selective is not None:  # the plain difference's own boxes
            out["selective"] = dataclasses.asdict(selective)
        return out

    def paired_options(self) -> Any:
        """The paired localizer's options: ``[detect.local]``, ``[detect.keypoints]``, defaults."""
        own = {"local": self.local, "keypoints": self.keypoints}
        return own.get(self.localizer) or LOCALIZER_KINDS[self.localizer].options()

    def local_localizer(self) -> LocalizerConfig | None:
        """The paired-frame localizer this run measures (None: the config's, ``"config"``)."""
        if self.localizer == CONFIG_LOCALIZERS:
            return None
        name = self.localizer
        return LocalizerConfig(name, name, (self.proposals,), self.paired_options())


def check_detect(
    dt: DetectConfig, where: str, typed: Mapping[str, str] | None = None, command: str = ""
) -> None:
    """``[detect]`` (method §13.1).

    ``typed``: field -> the flag its value came from, named with ``command`` in the error
    instead of ``where`` and the key.
    """
    flags = typed or {}

    def c(holds: bool, at: str, key: str, value: Any, allowed: str) -> None:
        typed_here = key in flags.values()
        check_value(holds, command if typed_here and command else at, key, value, allowed)

    def k(name: str) -> str:
        return flags.get(name, f"[detect] {name}")

    detect_rules = rules_where(detect=True)
    proposals = known_proposal_methods()
    # (holds, the field, what is allowed), checked in this order; the sections after them
    rules = [
        (dt.fusion in detect_rules, "fusion", ", ".join(detect_rules)),
        (0 < dt.nms_iou <= 1, "nms_iou", "(0, 1]"),
        (dt.max_boxes >= 1, "max_boxes", ">= 1 per frame"),
        (dt.chunk_frames >= 1, "chunk_frames", ">= 1"),
        (dt.threads >= 0, "threads", ">= 0 (0: one per core)"),
        (dt.top >= 0, "top", ">= 0 places"),
        (dt.boxes in BOX_GENERATORS, "boxes", f"one of {', '.join(BOX_GENERATORS)} (method §13.1)"),
        (dt.box_score in BOX_SCORES, "box_score", f"one of {', '.join(BOX_SCORES)}"),
        (0 < dt.alarm < 1, "alarm", "(0, 1): a false-alarm rate"),
        (dt.localizer in detect_localizers(), "localizer", " or ".join(detect_localizers())),
        (dt.calibration in CALIBRATIONS, "calibration", " or ".join(CALIBRATIONS)),
        (dt.not_comparable in NOT_COMPARABLE, "not_comparable", " or ".join(NOT_COMPARABLE)),
        (dt.bootstrap_group in BOOTSTRAP_GROUPS, "bootstrap_group", " or ".join(BOOTSTRAP_GROUPS)),
        (dt.proposals in proposals, "proposals", ", ".join(proposals)),
        (dt.box_prior in BOX_PRIORS, "box_prior", " or ".join(BOX_PRIORS)),
        (0 < dt.localization_weight <= 16, "localization_weight", "(0, 16]: a power of the score"),
        (0 < dt.locmap_level < 1, "locmap_level", "(0, 1): a share of each frame's LoC range"),
        (0 <= dt.min_box_side < 1e4, "min_box_side", "pixels a side, >= 0 (0: keep every box)"),
    ]
    for holds, name, allowed in rules:
        c(holds, where, k(name), getattr(dt, name), allowed)
    check_null(dt.null, f"{where} [detect.null]")
    check_local(dt.local, f"{where} [detect.local]")
    check_keypoints(dt.keypoints, f"{where} [detect.keypoints]")
    check_difference(dt.difference, f"{where} [detect.difference]")

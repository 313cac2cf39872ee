"""``harness detect``'s options (SPEC 13) and the proposals its local localizer ranks."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from harness.config.schema import Config
from harness.localizers.config import LocalConfig, LocalizerConfig
from harness.proposals.config import SegmentsConfig

log = logging.getLogger(__name__)


#: The proposal method ``harness detect``'s local localizer ranks: the frame's colour regions,
#: which meet most change objects (docs/method.md, *Detect*).
LOCAL_PROPOSALS = "segments"


@dataclass(frozen=True)
class DetectOptions:
    """``harness detect``'s choices (SPEC 13); defaults are SPEC's."""

    fusion: str = "rank_fusion"
    nms_iou: float = 0.5
    max_boxes: int = 10
    chunk_frames: int = 64  # query frames per cached unit (the unit a killed run resumes at)
    top: int = 10  # most changed places on the map and the page
    seed: int = 0
    boxes: str = "subimages"  # the box generator (SPEC 13.1, [detect] boxes)
    box_score: str = "max"  # locmap / proposals / segments: max, mean or contrast of the LoC
    locmap_level: float = 0.5  # locmap: the level, a share of the frame's LoC range
    min_box_side: float = 2.0  # [detect] min_box_side: thinner candidates are dropped
    segments: SegmentsConfig = field(default_factory=SegmentsConfig)  # [proposals.segments]
    localizer: str = "local"  # [detect] localizer: "local" (SPEC 13.3) or "config"
    box_prior: str = "area"  # [detect] box_prior: "area" or "none" (SPEC 13.3)
    local: LocalConfig = field(default_factory=LocalConfig)  # [detect.local]

    def record(self) -> dict[str, Any]:
        """The options as ``detect.json`` and the cache keys hold them (``segments`` where used)."""
        out = dataclasses.asdict(self)
        if self.boxes != "segments" and self.localizer != "local":
            del out["segments"]
        if self.localizer != "local":  # the paper's detector: its record (and keys) as before
            del out["local"], out["localizer"]
        return out

    def local_localizer(self) -> LocalizerConfig | None:
        """The local localizer ``[detect] localizer = "local"`` measures (None: the config's)."""
        if self.localizer != "local":
            return None
        return LocalizerConfig("local", "local", (LOCAL_PROPOSALS,), self.local)


@dataclass(frozen=True)
class DetectRun:
    """One detect run as its outputs read it: its pipeline, options and inputs (SPEC 13).

    ``p`` is the run's :class:`~harness.pipeline.chain.Pipeline` (its ``out``, ``ran`` and
    ``timings``); ``cfg`` the detect config; ``localizers`` the names whose ranks it fused;
    ``frames``, ``pairs`` and ``ann`` the frame table, the query frames' pairs with the map and the
    annotations (empty without); ``entries`` the detect chunks' cache entries; ``alarm`` the
    nominal false-alarm rate; ``alignment`` the local localizer's pairs (None without one).
    """

    p: Any
    cfg: Config
    opt: DetectOptions
    map_session: str
    queries: list[str]
    localizers: list[str]
    frames: pd.DataFrame
    pairs: pd.DataFrame
    ann: pd.DataFrame
    entries: list[Any]
    alarm: float = 0.01
    alignment: pd.DataFrame | None = None

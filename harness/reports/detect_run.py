"""One ``harness detect`` run as its outputs read it (its options are ``[detect]``'s record)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from harness.config.schema import Config
from harness.detect.config import DetectConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DetectRun:
    """One detect run as its outputs read it: its pipeline, options and inputs (method §13).

    ``p`` is the run's :class:`~harness.pipeline.chain.Pipeline` (its ``out``, ``ran`` and
    ``timings``); ``cfg`` the detect config; ``localizers`` the names whose ranks it fused;
    ``frames``, ``pairs`` and ``ann`` the frame table, the query frames' pairs with the map and the
    annotations (empty without); ``entries`` the detect chunks' cache entries; ``alarm`` the
    nominal false-alarm rate; ``alignment`` the local localizer's pairs (None without one);
    ``null`` the no-change null's scores (None: calibrated within the run).
    """

    p: Any
    cfg: Config
    opt: DetectConfig
    map_session: str
    queries: list[str]
    localizers: list[str]
    frames: pd.DataFrame
    pairs: pd.DataFrame
    ann: pd.DataFrame
    entries: list[Any]
    alarm: float = 0.01
    alignment: pd.DataFrame | None = None
    null: Any = (
        None  # the no-change null's scores (harness.detect.null.NullScores; None: within-run)
    )

    @property
    def folders(self) -> list[str]:
        """The folders' names, the map's first, where every session is a folder of images.

        ``--map-images``, ``--query-images``; else none.
        """
        by = {s.name: s for s in self.cfg.sessions}
        names = [self.map_session, *self.queries]
        if not all(n in by and by[n].format == "images" for n in names):
            return []
        return [Path(str(by[n].source)).name or str(by[n].source) for n in names]

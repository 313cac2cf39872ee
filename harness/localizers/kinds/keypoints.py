"""Kind ``keypoints``: each subimage's share of keypoints that do not localize in its map frame.

docs/decisions.md, *Keypoint localization*; :mod:`harness.localizers.keypoints`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from harness.localizers import stage as localizer_stage
from harness.localizers.config import KeypointConfig, LocalizerConfig, check_keypoints
from harness.localizers.kinds.base import LocalizerKind, LocalizerRun
from harness.localizers.kinds.local import costs
from harness.retrieval.config import RetrievalConfig
from harness.runtime.stage import RankTable, Table


def prepare(kc: KeypointConfig, where: str, base: Path, root: Path) -> KeypointConfig:
    """The ``keypoints`` table checked at load."""
    return check_keypoints(kc, f"{where}.keypoints")


def ranks(
    p: LocalizerRun,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    rc: RetrievalConfig,
) -> RankTable:
    """Units of ``frames_per_unit`` pairs, each writing its rank rows and its pairs' geometry.

    ``rc`` does not enter: the place is the paired frame itself.
    """
    del rc
    return localizer_stage.keypoint_ranks(p, loc.options, frames, pairs, mine)


def summary(rec: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The page's words: keypoint localization in the paired map frame (its features, geometry)."""
    kc = rec.get("keypoints") or {}
    how = f" ({kc.get('features')} keypoints, {kc.get('geometry')} geometry)" if kc else ""
    return f"keypoint localization, each subimage's keypoints matched in its paired map frame{how}"


#: Table L's costs as ``local``'s: no descriptor, no model, its map the map frames' pixels.
KIND = LocalizerKind(
    "keypoints",
    KeypointConfig,
    prepare,
    ranks=ranks,
    costs=costs,
    summary=summary,
    paired_frame=True,
)

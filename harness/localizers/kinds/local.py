"""Kind ``local``: each subimage ranked inside its paired map frame (method §13.3)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.imagestore import ImageRef
from harness.localizers import stage as localizer_stage
from harness.localizers.config import LocalConfig, LocalizerConfig, check_local
from harness.localizers.kinds.base import LocalizerKind, LocalizerRun
from harness.retrieval.config import RetrievalConfig
from harness.runtime.stage import RankTable, Table


def prepare(lc: LocalConfig, where: str, base: Path, root: Path) -> LocalConfig:
    """The ``local`` table checked at load."""
    return check_local(lc, f"{where}.local")


def ranks(
    p: LocalizerRun,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    rc: RetrievalConfig,
) -> RankTable:
    """Units of ``frames_per_unit`` pairs, each writing its rank rows and its pairs' alignments.

    ``rc`` does not enter: the place is the paired frame itself.
    """
    del rc
    return localizer_stage.local_ranks(p, loc.options, frames, pairs, mine)


def map_image_kib(frames: pd.DataFrame, pairs: pd.DataFrame) -> float:
    """The mean size (KiB) of the image files of the map frames ``pairs`` use."""
    used = frames.merge(
        pairs[["r_session", "r_camera", "r_utime"]].drop_duplicates(),
        left_on=["session", "camera", "utime"],
        right_on=["r_session", "r_camera", "r_utime"],
    )
    sizes = [Path(ImageRef.parse(u).path).stat().st_size for u in used["image"]]
    return float(np.mean(sizes)) / 1024.0 if sizes else float("nan")


def costs(cells: dict[str, float], frames: pd.DataFrame, pairs: pd.DataFrame) -> None:
    """Table L's cost cells of a ``local`` localizer: no descriptor, no model, no encoding.

    Its map is its pixels (the map frames' mean image file size); its rank time is the whole of
    its work (alignment and matching).
    """
    cells.update(descriptor_bytes=0.0, encode_ms=0.0, build_s=0.0)
    cells["map_kib_per_frame"] = map_image_kib(frames, pairs)


def summary(rec: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The page's words: each subimage ranked inside its paired map frame (its matching)."""
    lc = rec.get("local") or {}
    how = f" ({lc.get('keypoints')} keypoints, {lc.get('image')} image)" if lc else ""
    return f"local detection-by-localization, each subimage ranked in its paired map frame{how}"


KIND = LocalizerKind(
    "local", LocalConfig, prepare, ranks=ranks, costs=costs, summary=summary, paired_frame=True
)

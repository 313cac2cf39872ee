"""The fusion stage (method §7-8): ranks + annotations -> a sample per fused box, each rule's LoC.

Its key is made in :mod:`harness.fusion.keys`; the build is :func:`write_samples`, which labels
the samples from the annotations (:func:`labels_of`).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import pandas as pd

from harness.evaluate.config import SplitsConfig
from harness.evaluate.splits import roc_sob
from harness.fusion import keys as fusion_keys
from harness.fusion.config import FusionConfig
from harness.fusion.samples import Labels, fuse_samples
from harness.ingest.annotations import change_boxes
from harness.runtime.cache import read_cached_parquet, write_parquet
from harness.runtime.progress import progress
from harness.runtime.stage import RankTable, Table, Units


def labels_of(ann: pd.DataFrame) -> Labels:
    """The samples' labels from an annotation table: its change boxes, method §8's RoC and SoB."""
    return Labels(change_boxes(ann), roc_sob)


def write_samples(
    ranks: pd.DataFrame, frames: pd.DataFrame, ann: pd.DataFrame, fc: FusionConfig, tmp: Path
) -> dict[str, int]:
    """Build the labelled samples (:func:`fuse_samples`, ``[fusion]``) into ``samples.parquet``.

    Returns:
        The fusion counters (query images, capped closures).
    """
    df, counts = fuse_samples(
        ranks, frames, labels_of(ann), fc, progress=partial(progress, desc="fusion", unit="image")
    )
    write_parquet(tmp / "samples.parquet", df)
    return counts


def fused_samples(
    p: Units, fc: FusionConfig, sp: SplitsConfig, ranks: RankTable, frames: Table, ann: Table
) -> Table:
    """Ranks + annotations -> a sample per fused box with each fusion rule's LoC (method §7-8)."""
    build = partial(write_samples, ranks.df, frames.df, ann.df, fc)
    entry = p.unit("samples", fusion_keys.samples(fc, sp, ranks.key, ann.key), build)
    return Table(read_cached_parquet(entry.path / "samples.parquet"), entry.key)

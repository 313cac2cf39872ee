"""The fusion stage (method §7-8): ranks + annotations -> a sample per fused box, each rule's LoC.

Its key is made in :mod:`harness.fusion.keys`; the build is
:func:`harness.fusion.samples.write_samples`.
"""

from __future__ import annotations

from functools import partial

from harness.evaluate.config import SplitsConfig
from harness.fusion import keys as fusion_keys
from harness.fusion.config import FusionConfig
from harness.fusion.samples import write_samples
from harness.runtime.cache import read_cached_parquet
from harness.runtime.stage import RankTable, Table, Units


def fused_samples(
    p: Units, fc: FusionConfig, sp: SplitsConfig, ranks: RankTable, frames: Table, ann: Table
) -> Table:
    """Ranks + annotations -> a sample per fused box with each fusion rule's LoC (method §7-8)."""
    build = partial(write_samples, ranks.df, frames.df, ann.df, fc)
    entry = p.unit("samples", fusion_keys.samples(fc, sp, ranks.key, ann.key), build)
    return Table(read_cached_parquet(entry.path / "samples.parquet"), entry.key)

"""Retrieval (method §6): the rank engines and the ranking unit that feeds them.

:mod:`.engines` ranks by exact per-frame minima (its kernels in :mod:`.distances`, its exact
re-measurement in :mod:`.exact`, the layout it reads in :mod:`.layout`), :mod:`.faiss_search`
by a faiss top-k search; :mod:`.units` turns one reference session and a chunk of pairs into rank
rows.
"""

from __future__ import annotations

from harness.retrieval.distances import frame_min_sqdist_chunk
from harness.retrieval.engines import Engine, image_ranks
from harness.retrieval.faiss_search import FaissSearch, image_ranks_faiss
from harness.retrieval.layout import Ranks
from harness.retrieval.units import (
    RANK_COUNTS,
    described_frames,
    kept_reference_frames,
    rank_reference,
)

__all__ = [
    "RANK_COUNTS",
    "Engine",
    "FaissSearch",
    "Ranks",
    "described_frames",
    "frame_min_sqdist_chunk",
    "image_ranks",
    "image_ranks_faiss",
    "kept_reference_frames",
    "rank_reference",
]

"""Retrieval (SPEC section 6): the rank engines and the ranking unit that feeds them.

:mod:`.engines` holds the numeric kernels (exact per-frame minimum ranks, faiss top-k);
:mod:`.units` turns one reference session and a chunk of pairs into rank rows.
"""

from __future__ import annotations

from harness.retrieval.engines import Ranks, frame_min_sqdist_chunk, image_ranks, image_ranks_faiss
from harness.retrieval.units import (
    RANK_COUNTS,
    described_frames,
    kept_reference_frames,
    rank_reference,
)

__all__ = [
    "RANK_COUNTS",
    "Ranks",
    "described_frames",
    "frame_min_sqdist_chunk",
    "image_ranks",
    "image_ranks_faiss",
    "kept_reference_frames",
    "rank_reference",
]

"""The ranks' keys: a ranking unit, the rank table, an import, the bag-of-words' entries.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from harness.retrieval.config import BovwConfig, ImportConfig, RetrievalConfig
from harness.runtime.cache import Parts, content_sha, stable_hash

#: Retrieval options that only cut the ranking work into units.
RETRIEVAL_EXECUTION = ("query_frames_per_shard", "memory_mb")


def retrieval_options(rc: RetrievalConfig) -> dict[str, Any]:
    """The ``[retrieval]`` options that change ranks."""
    return {k: v for k, v in dataclasses.asdict(rc).items() if k not in RETRIEVAL_EXECUTION}


def ranks_unit(
    rc: RetrievalConfig,
    ref: str,
    pairs_key: str,
    descriptor_keys: dict[str, str],
    first: int,
    n: int,
    precision: str = "fp32",
) -> Parts:
    """One ranking unit: a reference session and ``n`` of its pairs from row ``first``.

    ``precision``: the engine's candidate product; ``bf16`` only adds to the key (fp32 keys as
    before it).
    """
    parts = (ref, pairs_key, descriptor_keys, retrieval_options(rc), first, n)
    return parts if precision == "fp32" else (*parts, {"precision": precision})


def ranks(
    rc: RetrievalConfig, pairs_key: str, descriptor_keys: dict[str, str], precision: str = "fp32"
) -> Parts:
    """The rank table's key (not a cache entry: what the samples depend on)."""
    parts = (pairs_key, descriptor_keys, retrieval_options(rc))
    return parts if precision == "fp32" else (*parts, {"precision": precision})


def rank_table(
    rc: RetrievalConfig, pairs_key: str, descriptor_keys: dict[str, str], precision: str = "fp32"
) -> str:
    """The key of the rank table the ranking units make together: :func:`ranks`' parts."""
    return stable_hash(*ranks(rc, pairs_key, descriptor_keys, precision))


def ranks_import(
    rc: RetrievalConfig,
    imp: ImportConfig,
    max_yaw_diff_deg: float,
    name: str,
    file: Path,
    pairs_key: str,
    proposal_keys: list[str],
    score_kind: str,
) -> Parts:
    """Ranks imported from a user's file.

    The file's content (not its path: a moved file is the same import), the pairs, the
    proposals the rows must match, the place and ``[import]`` with the localizer's
    ``score_kind``.
    """
    return (
        "import",
        name,
        content_sha(file),
        pairs_key,
        sorted(proposal_keys),
        rc.gt_radius_m,
        rc.db_stride_m,
        max_yaw_diff_deg,
        dataclasses.asdict(imp) | {"score_kind": score_kind},
    )


#: Bag-of-words options that only change how the work is cut or run.
BOVW_EXECUTION = ("num_workers", "shard_frames", "prefetch")


def bovw_options(bc: BovwConfig) -> dict[str, Any]:
    """The ``bovw`` options that change the vocabulary and the word vectors."""
    return {k: v for k, v in dataclasses.asdict(bc).items() if k not in BOVW_EXECUTION}


def bovw_vocab(bc: BovwConfig, reference_proposal_keys: list[str]) -> Parts:
    """A bag-of-words vocabulary: its options and the reference sessions' proposals it learns on."""
    return ("bovw_vocab", bovw_options(bc), sorted(reference_proposal_keys))


def bovw_shard(vocab_key: str, proposals_key: str, utimes: list[int]) -> Parts:
    """One shard of a session's word vectors: vocabulary, proposals, the shard's frames."""
    return (vocab_key, proposals_key, utimes[0], utimes[-1], len(utimes))


def bovw_words(vocab_key: str, proposals_key: str, shard_keys: list[str]) -> Parts:
    """A session's word vectors: the shards it stacks."""
    return (vocab_key, proposals_key, shard_keys)

"""The pairs' keys: by pose, by retrieval (its candidates), and their cut for ``harness detect``.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from harness.pairs.config import PairsConfig
from harness.runtime.cache import Parts, stable_hash


def pairs(pc: PairsConfig, seasons: dict[str, str], frames_key: str, ann_key: str) -> Parts:
    """Pairs: frames, ``[pairs]``, the seasons, and the annotations when they choose the queries."""
    return (
        frames_key,
        dataclasses.asdict(pc),
        ann_key if pc.queries == "annotated" else None,
        seasons,
    )


def candidates(pc: PairsConfig, seasons: dict[str, str], frames_key: str, ann_key: str) -> str:
    """The candidates that pairing by retrieval ranks: what pairs by pose would depend on."""
    return stable_hash("candidates", *pairs(pc, seasons, frames_key, ann_key))


def by_retrieval(candidates_key: str, descriptor_keys: dict[str, str], proposer: str) -> Parts:
    """Pairs by retrieval: the candidates, the descriptors ranked and the proposer they describe."""
    return (candidates_key, descriptor_keys, proposer)


def selected(tag: str, key: str, map_session: str, query_sessions: Sequence[str]) -> str:
    """Pairs (``tag``) cut to one map session and some query sessions (``harness detect``)."""
    return stable_hash(tag, key, map_session, sorted(query_sessions))

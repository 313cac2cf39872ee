"""The proposals' keys: a session's boxes and a localizer's subset of them.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from harness.proposals.config import ProposalsConfig
from harness.proposals.proposers import proposer_fingerprints
from harness.runtime.cache import Parts, file_fingerprint, stable_hash, without_empty

#: ``[proposals]`` options that change how the boxes are computed, not the boxes: in no key.
EXECUTION = ("threads",)


def proposals_file(pc: ProposalsConfig) -> Any:
    """The proposal file's fingerprint (its path alone when it does not exist)."""
    return file_fingerprint(Path(pc.file)) if pc.file and Path(pc.file).exists() else pc.file


def proposals(pc: ProposalsConfig, ingest_key: str, frames: list[tuple[str, int]]) -> Parts:
    """One session's proposals.

    Its ingest entry, the frames it describes (``frames``: their (camera, utime), from
    ``retrieval.described_frames``), ``[proposals]``, the proposal file and the source of any
    method registered from outside the package.
    """
    return (
        ingest_key,
        stable_hash(frames),
        without_empty(
            {k: v for k, v in dataclasses.asdict(pc).items() if k not in EXECUTION}, "options"
        ),
        proposals_file(pc),
        proposer_fingerprints(pc.methods),  # registered methods' own source
    )


def subset(table_key: str, methods: tuple[str, ...]) -> str:
    """The key of a proposal table cut to a localizer's ``methods`` (method §11)."""
    return stable_hash("proposal-subset", table_key, sorted(methods))

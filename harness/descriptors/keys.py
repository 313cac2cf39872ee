"""The descriptors' keys: the model, the projection and each session's shards.

A stage's entry lives under ``<out>/cache/<stage>/<key>/``: see :mod:`harness.runtime.cache`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from harness.descriptors.config import DescriptorConfig, ProjectionConfig
from harness.runtime.cache import Parts, content_sha
from harness.runtime.hardware import resolve_precision

#: Descriptor options that change neither the trained model nor the descriptors' values.
DESCRIPTOR_EXECUTION = (
    "num_workers",
    "shard_frames",
    "prefetch",
    "crop_threads",
    "trained_models",
)


#: ... and the ones that change the descriptors but not the model (the stored dtype, the batch).
MODEL_EXCLUDED = (*DESCRIPTOR_EXECUTION, "encode_batch", "dtype")


def _network(opts: dict[str, Any]) -> dict[str, Any]:
    """A user's network enters a key by its content, not its path (a moved file is the same)."""
    if opts.get("path"):
        opts["path"] = content_sha(Path(opts["path"]))
    return opts


def model_options(dc: DescriptorConfig) -> dict[str, Any]:
    """The ``[descriptor]`` options that change the trained model (``precision`` resolved)."""
    opts = {k: v for k, v in dataclasses.asdict(dc).items() if k not in MODEL_EXCLUDED}
    return _network(_precision(opts, dc))


def model(dc: DescriptorConfig, trains: bool, proposal_keys: list[str]) -> Parts:
    """The model: its options and (when it trains) the proposal entries it samples crops from."""
    if not trains:
        return (model_options(dc),)
    return (model_options(dc), sorted(proposal_keys))


def descriptor_options(dc: DescriptorConfig) -> dict[str, Any]:
    """The ``[descriptor]`` options that change descriptor values (``precision`` resolved)."""
    opts = {k: v for k, v in dataclasses.asdict(dc).items() if k not in DESCRIPTOR_EXECUTION}
    return _network(_precision(opts, dc))


def _precision(opts: dict[str, Any], dc: DescriptorConfig) -> dict[str, Any]:
    """``opts`` with ``precision`` as it resolves here: absent for fp32 (the keys of before)."""
    if resolve_precision(dc.precision, dc.device) == "fp32":
        opts.pop("precision", None)
    else:
        opts["precision"] = "bf16"
    return opts


def descriptor_shard(
    dc: DescriptorConfig,
    proposals_key: str,
    model_key: str,
    utimes: list[int],
    projection_key: str | None,
) -> Parts:
    """One shard of a session's descriptors.

    Proposals, model, options, the shard's frames (and the projection).
    """
    parts = (
        proposals_key,
        model_key,
        descriptor_options(dc),
        utimes[0],
        utimes[-1],
        len(utimes),
    )
    return parts if projection_key is None else (*parts, projection_key)


def descriptors(
    dc: DescriptorConfig, proposals_key: str, model_key: str, shard_keys: list[str]
) -> Parts:
    """A session's combined descriptors: the shards it copies."""
    return (proposals_key, model_key, descriptor_options(dc), shard_keys)


def projection(
    pc: ProjectionConfig, dc: DescriptorConfig, model_key: str, reference_proposal_keys: list[str]
) -> Parts:
    """The compact-descriptor projection.

    ``[projection]``, the model and the reference sessions' proposals.
    """
    return (
        dataclasses.asdict(pc),
        model_key,
        descriptor_options(dc),
        sorted(reference_proposal_keys),
    )

"""Every stage's cache key, in one place.

A stage entry lives under ``<out>/cache/<stage>/<key>/``, where ``key`` is a hash of the parts
returned here plus :data:`harness.runtime.cache.CODE_FINGERPRINT` (so new code never reuses old
results). A part is what the stage's output depends on: the keys of the entries it reads and the
config sections it uses. Options that only change *how* a stage runs (workers, shard and batch
sizes, the device) stay out, so changing them reuses every entry. ``docs/architecture.md`` lists
them.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from harness.config.schema import Config
from harness.descriptors.config import DescriptorConfig, ProjectionConfig
from harness.fusion.fuse import method_fingerprints as fusion_method_fingerprints
from harness.ingest.config import SessionConfig
from harness.ingest.logs import READERS, detect_format
from harness.proposals.config import ProposalsConfig
from harness.proposals.proposers import method_fingerprints
from harness.retrieval.config import BovwConfig, RetrievalConfig
from harness.runtime.cache import content_sha, file_fingerprint, relative_to_root, stable_hash
from harness.runtime.hardware import resolve_precision

Parts = tuple[Any, ...]

#: Descriptor options that change neither the trained model nor the descriptors' values.
DESCRIPTOR_EXECUTION = ("num_workers", "shard_frames", "prefetch")
#: ... and the ones that change the descriptors but not the model (the stored dtype, the batch).
MODEL_EXCLUDED = (*DESCRIPTOR_EXECUTION, "encode_batch", "dtype")
#: Retrieval options that only cut the ranking work into units.
RETRIEVAL_EXECUTION = ("query_frames_per_shard", "memory_mb")


def source_fingerprint(sc: SessionConfig, root: Path | None = None) -> Any:
    """Identity of a session's source: only the files that session reads (paths, sizes, mtimes).

    Paths enter relative to the data root ``root``, so a moved data root keeps every key.
    """
    src = Path(sc.source)
    fmt = detect_format(src) if sc.format == "auto" else sc.format
    rec = READERS.get(fmt)
    if rec is not None and rec.sources is not None:  # a layout: only the files it reads
        return {name: file_fingerprint(path, root) for name, path in rec.sources(sc).items()}
    return file_fingerprint(src, root)


def ingest(cfg: Config, sc: SessionConfig) -> Parts:
    """One session's ingest: its config (source relative to the data root), ``[ingest]``, files."""
    session = {**dataclasses.asdict(sc), "source": relative_to_root(sc.source, cfg.data_root)}
    return (
        "ingest",
        session,
        dataclasses.asdict(cfg.ingest),
        source_fingerprint(sc, cfg.data_root),
    )


def frames(ingest_keys: list[str]) -> Parts:
    """The frame table: the ingest entries it concatenates."""
    return tuple(ingest_keys)


def pairs(cfg: Config, frames_key: str, ann_key: str) -> Parts:
    """Pairs: frames, ``[pairs]``, the seasons, and the annotations when they choose the queries."""
    pc = cfg.pairs
    return (
        frames_key,
        dataclasses.asdict(pc),
        ann_key if pc.queries == "annotated" else None,
        cfg.seasons(),
    )


def proposals_file(pc: ProposalsConfig) -> Any:
    """The proposal file's fingerprint (its path alone when it does not exist)."""
    return file_fingerprint(Path(pc.file)) if pc.file and Path(pc.file).exists() else pc.file


def proposals(cfg: Config, ingest_key: str, frames: list[tuple[str, int]]) -> Parts:
    """One session's proposals.

    Its ingest entry, the frames it describes (``frames``: their (camera, utime), from
    ``retrieval.described_frames``), ``[proposals]``, the proposal file and the source of any
    method registered from outside the package.
    """
    return (
        ingest_key,
        stable_hash(frames),
        _without_empty(dataclasses.asdict(cfg.proposals), "options"),
        proposals_file(cfg.proposals),
        method_fingerprints(cfg.proposals.methods),  # registered methods' own source
    )


def _without_empty(opts: dict[str, Any], name: str) -> dict[str, Any]:
    """``opts`` without ``name`` when it is empty (a key from before the field keeps its value)."""
    return {k: v for k, v in opts.items() if k != name or v}


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


def ranks_import(
    cfg: Config,
    rc: RetrievalConfig,
    name: str,
    content_sha: str,
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
        content_sha,
        pairs_key,
        sorted(proposal_keys),
        rc.gt_radius_m,
        rc.db_stride_m,
        cfg.pairs.max_yaw_diff_deg,
        dataclasses.asdict(cfg.import_) | {"score_kind": score_kind},
    )


def samples(cfg: Config, ranks_key: str, ann_key: str) -> Parts:
    """Samples: ranks, annotations, ``[fusion]``, ``[splits]`` (and registered methods' source)."""
    return (
        ranks_key,
        ann_key,
        _without_empty(dataclasses.asdict(cfg.fusion), "options"),
        dataclasses.asdict(cfg.splits),
        fusion_method_fingerprints(cfg.fusion.methods),
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


def local_ranks(lc: Any, pairs_key: str, proposal_keys: list[str], c0: int, n: int) -> Parts:
    """A unit of a local localizer's ranks: its options (less the unit size), pairs, proposals."""
    opts = {k: v for k, v in dataclasses.asdict(lc).items() if k != "frames_per_unit"}
    return ("local_ranks", opts, pairs_key, proposal_keys, c0, n)


def subset(table_key: str, methods: tuple[str, ...]) -> str:
    """The key of a proposal table cut to a localizer's ``methods`` (SPEC section 11)."""
    return stable_hash("proposal-subset", table_key, sorted(methods))

"""Kind ``descriptor``: a learned or given descriptor, ranked by the engine (method §6, 11).

Its options are ``[descriptor]``'s table; its ranks: the model, the projection, each session's
descriptors, then the ranking engine.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from harness.descriptors.config import DescriptorConfig
from harness.descriptors.stage import session_descriptors
from harness.inputs import resolve_config_path
from harness.localizers.config import LocalizerConfig
from harness.localizers.kinds.base import LocalizerKind, LocalizerRun, options_of
from harness.retrieval.config import RetrievalConfig
from harness.runtime.stage import RankTable, Table


def prepare(de: DescriptorConfig, where: str, base: Path, root: Path) -> DescriptorConfig:
    """A user's network path and the trained models' folder resolved against the config's."""
    if de.path:
        de = dataclasses.replace(de, path=str(resolve_config_path(de.path, base, root)))
    if de.trained_models:
        kept = resolve_config_path(de.trained_models, base, root)
        de = dataclasses.replace(de, trained_models=str(kept))
    return de


def record(de: DescriptorConfig) -> dict[str, Any]:
    """What ``run.json`` says of a descriptor localizer: the descriptor's name."""
    return {"descriptor": de.name}


def ranks(
    p: LocalizerRun,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    mine: dict[str, Table],
    rc: RetrievalConfig,
) -> RankTable:
    """Model, projection, descriptors, then the ranking engine."""
    dc = options_of(loc, loc.descriptor)
    model = p.descriptor_model(dc, frames, mine)
    projection = p.descriptor_projection(dc, frames, pairs, mine, model)
    described = session_descriptors(p, dc, frames, mine, model, projection)
    return p.query_ranks(frames, pairs, described, rc, dc.device, dc.precision)


def summary(rec: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The page's words: the descriptor (the run's ``[descriptor]`` where the record is short)."""
    return "built-in descriptor " + str(
        rec.get("descriptor") or cfg.get("descriptor", {}).get("name")
    )


KIND = LocalizerKind("descriptor", DescriptorConfig, prepare, record, ranks, summary=summary)

"""The ranking stages as the localizers call them: with ``[pairs]``, ``[import]`` and the sessions.

The stages are :func:`harness.retrieval.stage.rank_queries` and
:func:`harness.retrieval.stage.imported_ranks`.
"""

from __future__ import annotations

import dataclasses

from harness.pipeline.context import Context
from harness.retrieval import stage as retrieval_stage
from harness.retrieval.config import RetrievalConfig
from harness.retrieval.import_file import ImportSpec
from harness.retrieval.units import RankSettings
from harness.runtime.hardware import rank_precision
from harness.runtime.stage import Entry, RankTable, Table


def ranks_device(rc: RetrievalConfig, dev: str) -> str:
    """The exact engine's device: CUDA when ``dev`` (the descriptor's) allows it and one exists."""
    import torch

    return (
        "cuda"
        if rc.engine == "exact" and dev in ("auto", "cuda") and torch.cuda.is_available()
        else "cpu"
    )


def query_ranks(
    p: Context,
    frames: Table,
    pairs: Table,
    described: dict[str, Entry],
    rc: RetrievalConfig,
    device: str = "auto",
    precision: str = "fp32",
) -> RankTable:
    """Pairs + descriptors -> the rank of each query subimage's ground-truth place (SPEC section 6).

    ``rc``: the ``[retrieval]`` to rank under (the run's, or ``gt_radius_also``'s). ``device``:
    the descriptor's (``[descriptor] device``); the exact engine runs on CUDA where it allows and
    one is present. ``precision``: the descriptor's (``[descriptor] precision``), for the exact
    engine's candidate product (:func:`harness.runtime.hardware.rank_precision`). By retrieval
    (SPEC 13.2) the place is ``[pairs] place_frames`` frames each side.
    """
    pc = p.cfg.pairs
    how = RankSettings(
        rc,
        pc.max_yaw_diff_deg,
        ranks_device(rc, device),
        pc.place_frames if pc.by != "pose" else None,
        rank_precision(precision) if rc.engine == "exact" else "fp32",
    )
    refs = [s.name for s in p.cfg.sessions]
    return retrieval_stage.rank_queries(p, how, refs, frames, pairs, described)


def imported_ranks(
    p: Context,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
    spec: ImportSpec,
    score_kind: str,
    rc: RetrievalConfig,
) -> RankTable:
    """Ranks from a user's file, scored as ``score_kind``.

    :func:`harness.retrieval.stage.imported_ranks` under the run's ``[import]`` and heading limit.
    """
    imp = dataclasses.replace(p.cfg.import_, score_kind=score_kind)
    yaw = p.cfg.pairs.max_yaw_diff_deg
    return retrieval_stage.imported_ranks(p, rc, imp, yaw, frames, pairs, props, spec)

"""The ranking stages as a localizer kind of a user's calls them: the run's methods, as functions.

``query_ranks(p, ...)`` is ``p.query_ranks(...)`` and ``imported_ranks(p, ...)`` is
``p.imported_ranks(...)`` (:class:`harness.pipeline.context.Context`), kept for the plugins that
import them (``examples/plugins/colour.py``).
"""

from __future__ import annotations

from harness.pipeline.context import Context
from harness.retrieval.config import RetrievalConfig
from harness.retrieval.import_file import ImportSpec
from harness.runtime.stage import Entry, RankTable, Table


def query_ranks(
    p: Context,
    frames: Table,
    pairs: Table,
    described: dict[str, Entry],
    rc: RetrievalConfig,
    device: str = "auto",
    precision: str = "fp32",
) -> RankTable:
    """Pairs + descriptors -> ranks (:meth:`harness.pipeline.context.Context.query_ranks`)."""
    return p.query_ranks(frames, pairs, described, rc, device, precision)


def imported_ranks(
    p: Context,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
    spec: ImportSpec,
    score_kind: str,
    rc: RetrievalConfig,
) -> RankTable:
    """Ranks from a user's file (:meth:`harness.pipeline.context.Context.imported_ranks`)."""
    return p.imported_ranks(frames, pairs, props, spec, score_kind, rc)

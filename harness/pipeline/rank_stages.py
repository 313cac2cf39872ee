"""The ranking stages as functions of the run, for the plugins that call them so.

``query_ranks(p, ...)`` is ``p.query_ranks(...)`` and ``imported_ranks(p, ...)`` is
``p.imported_ranks(...)``: the run's own methods (:class:`harness.pipeline.context.Context`),
named here so the plugins written before them keep working.
"""

from __future__ import annotations

from harness.pipeline.context import Context

query_ranks = Context.query_ranks
imported_ranks = Context.imported_ranks

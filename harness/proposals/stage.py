"""The proposals stage (method §5): each session's boxes, on the frames ranking reads.

Its key is made in :mod:`harness.proposals.keys`; the methods are in :mod:`.builtin`, :mod:`.yolo`
and :mod:`.file`, run by :func:`harness.proposals.proposers.write_proposals`.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import pandas as pd

from harness.proposals import keys as proposal_keys
from harness.proposals.config import ProposalsConfig
from harness.proposals.proposers import write_proposals
from harness.runtime.cache import read_cached_parquet
from harness.runtime.stage import Entry, Table, Units


def session_proposals(
    p: Units,
    pc: ProposalsConfig,
    sessions: Sequence[str],
    described: dict[str, pd.DataFrame],
    ingested: dict[str, Entry],
) -> dict[str, Table]:
    """The frames each session's ranking reads -> the session's proposal boxes (method §5).

    ``described``: each session's frames (rows of the frame table); one entry per session.
    """
    out = {}
    for name in sessions:
        fr = described[name]
        build = partial(write_proposals, fr, pc, name)
        used = [(str(c), int(u)) for c, u in zip(fr["camera"], fr["utime"], strict=True)]
        entry = p.unit("proposals", proposal_keys.proposals(pc, ingested[name].key, used), build)
        out[name] = Table(read_cached_parquet(entry.path / "proposals.parquet"), entry.key)
    return out

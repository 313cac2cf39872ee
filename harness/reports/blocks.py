"""The records of a run's reports: a block of the tables, and what the reports hold."""

from __future__ import annotations

from dataclasses import dataclass, field

import pandas as pd


@dataclass
class Block:
    """One block of the tables: a localizer's boxes, or every localizer's (``all localizers``).

    ``ranks`` is None for the cross-localizer block (it has no localization table of its own);
    ``methods`` are the fusion methods computed for it; ``notes`` are printed under its tables.
    """

    name: str
    samples: pd.DataFrame
    ranks: pd.DataFrame | None
    methods: tuple[str, ...]
    notes: list[str] = field(default_factory=list)
    # Table L's cost cells (harness.runtime.costs)
    costs: dict[str, float] = field(default_factory=dict)
    ranks_also: pd.DataFrame | None = None  # the ranks at [report] gt_radius_also


@dataclass
class Reports:
    """What a run's reports hold, for the caller to print.

    With several localizers, ``blocks`` holds each block's own :class:`Reports` (the fields
    above hold their concatenation, or the first block's tables) and ``table_l`` the leaderboard.
    """

    summary: pd.DataFrame
    localization: pd.DataFrame
    tables: dict[str, pd.DataFrame]
    warnings: dict[str, list[str]]
    methods: tuple[str, ...]
    localizer: str = ""
    blocks: list[Reports] = field(default_factory=list)
    table_l: pd.DataFrame | None = None
    costs: dict[str, float] = field(default_factory=dict)
    localization_also: pd.DataFrame | None = None  # at [report] gt_radius_also

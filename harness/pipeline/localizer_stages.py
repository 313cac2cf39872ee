"""The stages of a run's localizers (method §11).

Each localizer's ranks, the fusion methods it can have, the same query images for all, and the
``all localizers`` box list.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

from harness.descriptors.stage import session_descriptors
from harness.errors import ConfigError
from harness.fusion.config import FusionConfig
from harness.localizers.config import LocalizerConfig
from harness.localizers.kinds import LOCALIZER_KINDS, options_of
from harness.pipeline.context import Context
from harness.pipeline.stages import retrieval_pair_table
from harness.proposals import keys as proposal_keys
from harness.retrieval.config import RetrievalConfig
from harness.runtime.costs import localizer_costs
from harness.runtime.stage import RankTable, Table

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- localizers (method §11)


@dataclass
class Measured:
    """One localizer's ranks, the fusion methods it can have, and what its tables must say."""

    loc: LocalizerConfig
    ranks: RankTable
    fusion: FusionConfig
    notes: list[str] = field(default_factory=list)
    # Table L's cost cells (harness.runtime.costs)
    costs: dict[str, float] = field(default_factory=dict)
    ranks_also: RankTable | None = None  # at [report] gt_radius_also (the localization table)


def localizer_proposals(
    p: Context, loc: LocalizerConfig, props: dict[str, Table]
) -> dict[str, Table]:
    """Each session's proposals cut to the localizer's methods (as they are when it uses all)."""
    if set(loc.proposals) == set(p.cfg.proposals.methods):
        return props
    return {
        s: Table(
            t.df[t.df["proposal_method"].isin(loc.proposals)].reset_index(drop=True),
            proposal_keys.subset(t.key, loc.proposals),
        )
        for s, t in props.items()
    }


def localizer_ranks(
    p: Context,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
    rc: RetrievalConfig | None = None,
) -> RankTable:
    """One localizer's rank rows: its kind's stages over its proposals (method §6, 11, 12).

    ``rc``: the ``[retrieval]`` to rank under (None: the run's).
    """
    mine = localizer_proposals(p, loc, props)
    ranks = LOCALIZER_KINDS[loc.kind].ranks
    if ranks is None:
        raise ConfigError(f"localizer kind {loc.kind!r} was registered without a ranks function")
    return ranks(p, loc, frames, pairs, mine, p.cfg.retrieval if rc is None else rc)


def retrieval_ranks(
    p: Context, loc: LocalizerConfig, frames: Table, cand: Table, props: dict[str, Table]
) -> tuple[Table, RankTable]:
    """Pairs by retrieval, then ranks, with one descriptor localizer (method §13.2).

    The localizer's descriptors of every candidate frame pair each query frame with its map
    frame (its first proposal method's subimages); the ranks are then computed as by pose, the
    place being that frame and ``[pairs] place_frames`` neighbours each side.

    Returns:
        (the pairs, the rank rows).
    """
    if loc.kind != "descriptor":
        raise ConfigError(
            f"[pairs] by = 'retrieval' pairs frames with the run's descriptor; localizer "
            f"{loc.name} is of kind {loc.kind!r}"
        )
    mine, dc = localizer_proposals(p, loc, props), options_of(loc, loc.descriptor)
    model = p.descriptor_model(dc, frames, mine)
    projection = p.descriptor_projection(dc, frames, cand, mine, model)
    described = session_descriptors(p, dc, frames, mine, model, projection)
    pairs = retrieval_pair_table(p, frames, cand, described, loc.proposals[0])
    return pairs, p.query_ranks(frames, pairs, described, p.cfg.retrieval, dc.device, dc.precision)


def ranks_at_radius(
    p: Context,
    radius_m: float,
    loc: LocalizerConfig,
    frames: Table,
    pairs: Table,
    props: dict[str, Table],
) -> RankTable:
    """A localizer's ranks with the ground-truth place ``radius_m`` wide (``gt_radius_also``).

    The same descriptors (their keys do not hold the radius), ranked again under the other place.
    """
    rc = dataclasses.replace(p.cfg.retrieval, gt_radius_m=radius_m)
    return localizer_ranks(p, loc, frames, pairs, props, rc)


def measured_costs(
    p: Context,
    loc: LocalizerConfig,
    trail: list[tuple[str, Path]],
    ranks: RankTable,
    pairs: Table,
    props: dict[str, Table],
    frames: Table | None = None,
) -> dict[str, float]:
    """Table L's cost cells of a localizer from the entries its stages used (``trail``).

    Its kind's record may adjust them, given ``frames`` (``local``: its map is the map frames'
    image files, and it encodes and builds nothing).
    """
    mine = localizer_proposals(p, loc, props)
    refs = sorted(set(pairs.df["r_session"]))
    ref_rows = [mine[s].df for s in refs if s in mine]
    ref_sub = sum(len(df) for df in ref_rows)
    ref_frames = sum(len(df[["camera", "utime"]].drop_duplicates()) for df in ref_rows)
    costs = localizer_costs(
        trail, len(ranks.df), ref_sub, ref_frames, imported=loc.import_ is not None
    )
    adjust = LOCALIZER_KINDS[loc.kind].costs
    if adjust is not None and frames is not None:
        adjust(costs, frames.df, pairs.df)
    return costs

"""Method §11's cross-localizer block: the localizers compared on the query images all of them rank.

Each localizer's fused LoC on those images, and the fusion across localizers.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np
import pandas as pd

from harness.errors import RetrievalError
from harness.fusion.config import FusionConfig
from harness.localizers import keys as localizer_keys
from harness.localizers.config import LocalizerConfig
from harness.methods import rules_where
from harness.pipeline.context import Context
from harness.pipeline.localizer_stages import Measured
from harness.records import IMAGE_KEY
from harness.retrieval.stage import concat_ranks
from harness.runtime.stage import RankTable, Table

log = logging.getLogger(__name__)


def localizer_fusion(
    p: Context, loc: LocalizerConfig, ranks: RankTable, n_images: int
) -> tuple[FusionConfig, list[str]]:
    """The fusion methods a localizer can have, and the notes its tables carry.

    A localizer without a relevance score (an imported list without ``scores``) gets no score
    method (never NaN rows without a word); lost images and truncated lists are noted.
    """
    notes: list[str] = []
    fc = p.cfg.fusion
    info = ranks.counts.get("import", {})
    has_d = loc.import_ is None or bool(info.get("has_scores"))
    if not has_d:
        dropped = [m for m in rules_where(needs_score=True) if m in fc.methods]
        kept = tuple(m for m in fc.methods if m not in dropped)
        if dropped and kept:
            fc = dataclasses.replace(fc, methods=kept)
        if dropped:
            notes.append(
                f"NOTE: {', '.join(dropped)} not computed: localizer {loc.name} gives ranked "
                "lists without scores, so it has no relevance score d (method §11-12)."
            )
    lost = int(info.get("unranked_query_images", 0))
    if lost:
        notes.append(
            f"NOTE: {lost} of {n_images} query images have no row from localizer {loc.name} "
            "and are left out of every table ([import] allow_unranked_images = true)."
        )
    inexact = int(info.get("gt_missing_from_truncated_list", 0))
    if inexact:
        share = inexact / max(len(ranks.df), 1)
        log.warning(  # once on the console; each of the localizer's tables carries the note
            "%d of %d query subimages (%.0f%%) of localizer %s have a truncated list without "
            "their place: their rank is a bound (exact = False), and every figure of this "
            "localizer rests on bounds, not ranks (Table L marks it [bounds])",
            inexact,
            len(ranks.df),
            100 * share,
            loc.name,
        )
        notes.append(
            f"NOTE: {inexact} of {len(ranks.df)} query subimages of localizer {loc.name} have a "
            "truncated list without their place: their rank is a bound (exact = False)."
        )
    nofeat = int(ranks.counts.get("bovw", {}).get("no_feature_subimages", 0))
    if nofeat:
        notes.append(
            f"NOTE: {nofeat} subimages had no local feature under localizer {loc.name}: they "
            "are neither queries nor database rows of its engine (method §11)."
        )
    return fc, notes


def common_images(p: Context, measured: list[Measured], pairs: Table) -> str | None:
    """Score every localizer on the same query images (method §11).

    A query image of the pairs that some localizer did not rank is an error naming the
    localizer and the image, unless ``[import] allow_unranked_images``: then it is left out of
    every localizer's ranks, and the returned note says how many.

    Raises:
        RetrievalError: an unranked image (not allowed).
    """
    all_images = pd.MultiIndex.from_frame(pairs.df[IMAGE_KEY])
    keep = np.ones(len(all_images), bool)
    first_missing: tuple[str, Any] | None = None
    for m in measured:
        got = pd.MultiIndex.from_frame(m.ranks.df[IMAGE_KEY].drop_duplicates())
        has = all_images.isin(got)
        if first_missing is None and not has.all():
            first_missing = (m.loc.name, all_images[np.flatnonzero(~has)[0]])
        keep &= has
    if keep.all():
        return None
    lost = int((~keep).sum())
    name, ex = first_missing or ("?", ("?", "?", "?", "?"))  # set where keep first went False
    if not p.cfg.import_.allow_unranked_images:
        raise RetrievalError(
            f"localizer {name!r} ranks no subimage of query image {ex[0]}/{ex[1]}/{ex[2]} -> "
            f"{ex[3]} ({lost} of {len(all_images)} query images lack some localizer's rank); "
            "every localizer is scored on the same images: set [import] allow_unranked_images "
            "= true to leave them out of every table (counted)"
        )
    kept = pd.MultiIndex.from_frame(pairs.df[IMAGE_KEY][keep])
    for m in measured:
        df = m.ranks.df
        sel = pd.MultiIndex.from_frame(df[IMAGE_KEY]).isin(kept)
        if not sel.all():
            m.ranks = RankTable(
                df[sel].reset_index(drop=True),
                localizer_keys.common_images(m.ranks.key, int((~sel).sum())),
                m.ranks.counts,
            )
    return (
        f"NOTE: {lost} of {len(all_images)} query images lack a rank from at least one "
        f"localizer (e.g. {name}: {ex[0]}/{ex[1]}/{ex[2]}) and are left out of every row "
        "([import] allow_unranked_images = true)."
    )


def across_localizers(measured: list[Measured]) -> RankTable:
    """Every localizer's rank rows as one list of original boxes (method §11).

    An original box is the pair (localizer, box): its method becomes ``localizer:method``, and
    ``d`` is dropped (scores of different localizers are not comparable).
    """
    parts = [
        m.ranks.df.assign(
            proposal_method=m.loc.name + ":" + m.ranks.df["proposal_method"].astype(str), d=np.nan
        )
        for m in measured
    ]
    df = concat_ranks(parts)
    return RankTable(df, localizer_keys.all_localizers([m.ranks.key for m in measured]), {})

"""Pooled APs with bootstrap intervals and paired differences (method §9).

Table I and S columns (:func:`pooled_rows`), the per-proposal and per-season-pair breakdowns
(:func:`table_i_rows`); Table P's pixel and image APs are :mod:`harness.evaluate.pixel_aps`.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from functools import partial

import numpy as np
import pandas as pd

from harness.evaluate import chance
from harness.evaluate.config import EvalSettings
from harness.evaluate.metrics import (
    average_precision,
    bootstrap_aps,
    interval,
    paired_difference,
    resample_counts,
    stratified_ap,
)
from harness.evaluate.splits import Split
from harness.evaluate.splits import label as split_label


def sample_groups(df: pd.DataFrame) -> np.ndarray:
    """Each sample's query image and reference session as one group id (the bootstrap's unit)."""
    return (
        df["q_session"].astype(str)
        + "|"
        + df["q_camera"].astype(str)
        + "|"
        + df["q_utime"].astype(str)
        + "|"
        + df["r_session"].astype(str)
    ).to_numpy()


def query_frames(groups: np.ndarray) -> int:
    """The query frames among sample groups (``q_session|q_camera|q_utime|r_session``).

    One frame paired with three reference sessions is three bootstrap units but one piece of
    evidence: method §9's *evidence before a verdict* counts frames.
    """
    return len({str(g).rsplit("|", 1)[0] for g in np.unique(np.asarray(groups, dtype=object))})


def stratified_labels(roc: np.ndarray, split: Split) -> np.ndarray:
    """Method §8's size-stratified labels.

    By RoC only (+1 positive, 0 negative, -1 left out).
    """
    pos = (roc >= split.pos_roc[0]) & (roc <= split.pos_roc[1])
    neg = (roc >= split.neg_roc[0]) & (roc <= split.neg_roc[1])
    out = np.full(len(roc), -1, np.int8)
    out[neg] = 0
    out[pos] = 1
    return out


class Pooled:
    """Pooled APs of one table column for every method, with bootstrap intervals.

    Also the paired comparison with ``rank_fusion`` over the same resampled query images.
    """

    def __init__(self, cfg: EvalSettings, image_ids: dict[str, int], column: str) -> None:
        self.cfg, self.ids, self.column = cfg, image_ids, column
        self.counts = resample_counts(
            len(image_ids), cfg.report.bootstrap, cfg.seed + (zlib.crc32(column.encode()) % 10_000)
        )
        self.rows: list[dict] = []
        self.boot: dict[str, np.ndarray] = {}

    def add(
        self, fusion_rule: str, row: dict, boot_fn: Callable[[np.ndarray], np.ndarray] | None
    ) -> None:
        """``boot_fn(counts)`` gives the method's AP in every resample (None: no interval)."""
        b = boot_fn(self.counts) if boot_fn is not None and len(self.counts) else np.full(0, np.nan)
        lo, hi = interval(b, self.cfg.report.ci)
        self.boot[fusion_rule] = b
        self.rows.append({**row, "fusion": fusion_rule, "ci_low": lo, "ci_high": hi})

    def finish(self) -> list[dict]:
        """Each row's paired differences from ``rank_fusion`` and from ``random``, and its verdict.

        Both differences use the same resamples; the verdict is method §9's one rule
        (:func:`harness.evaluate.chance.verdict`).
        """
        for r in self.rows:
            r.update(self._paired(r, "rank_fusion", ""))
            r.update(self._paired(r, "random", "vs_random_"))
            evidence = chance.Evidence(
                int(r["positive_images"]), self.cfg.report.min_positive_images
            )
            r["positive_images_needed"] = evidence.needed
            r["verdict"] = chance.verdict(
                r["ap"],
                r["chance_low"],
                r["chance_high"],
                r["vs_random_diff_ci_low"],
                r["vs_random_diff_ci_high"],
                evidence,
            )
        return self.rows

    def _paired(self, r: dict, ref_method: str, prefix: str) -> dict[str, float]:
        """``r``'s method minus ``ref_method`` over the same resamples (NaN where undefined)."""
        ref = next((x for x in self.rows if x["fusion"] == ref_method), None)
        nan = float("nan")
        out = dict.fromkeys(
            ("diff", "diff_ci_low", "diff_ci_high", "sign_flip_share", "p_value"), nan
        )
        same = r["fusion"] == ref_method and prefix == ""
        if ref is not None and not same and len(self.boot[r["fusion"]]):
            out = paired_difference(
                self.boot[r["fusion"]],
                self.boot[ref_method],
                r["ap"],
                ref["ap"],
                self.cfg.report.ci,
            )
        return {f"{prefix}{k}": v for k, v in out.items()}


def chance_fields(
    floor: tuple[float, float, float], ap: float, ceiling: float = float("nan")
) -> dict[str, float]:
    """A row's floor, chance band, ceiling and share of the reachable gap (method §9)."""
    f, lo, hi = floor
    return {
        "floor": f,
        "chance_low": lo,
        "chance_high": hi,
        "ceiling": ceiling,
        "gap_closed": chance.gap_closed(ap, f, ceiling),
    }


def table_i_rows(
    df: pd.DataFrame,
    split: Split,
    methods: tuple[str, ...],
    season_pair: str,
    proposals: str,
    draws: int = chance.MIN_DRAWS,
    seed: int = 0,
    min_positive_images: int = chance.MIN_POSITIVE_IMAGES,
) -> list[dict]:
    """Per-split APs without intervals (the breakdowns by proposal method and season pair).

    Their floors and chance bands are measured like the pooled ones; without a bootstrap their
    verdict is ``untested`` (``few`` where their positives sit in too few query images).
    """
    nan = float("nan")
    rows = []
    lab = split_label(df["RoC"].to_numpy(), df["SoB"].to_numpy(), split)
    groups = sample_groups(df)
    for m in methods:
        loc = df[f"loc_{m}"].to_numpy()
        sel = (lab >= 0) & ~np.isnan(loc)
        y = lab[sel] == 1
        ap = average_precision(y, loc[sel])
        floor = chance.plain_chance(y, draws, seed)
        pos_images = query_frames(groups[sel][y])
        evidence = chance.Evidence(pos_images, min_positive_images)
        rows.append(
            {
                "table": "I",
                "split": split.name,
                "roc_max": split.roc_max,
                "proposal_method": proposals,
                "season_pair": season_pair,
                "fusion": m,
                "ap": ap,
                **chance_fields(floor, ap),
                "ci_low": float("nan"),
                "ci_high": float("nan"),
                "positives": int(y.sum()),
                "negatives": int((~y).sum()),
                "left_out": int(((lab < 0) & ~np.isnan(loc)).sum()),
                "positive_rate": float(y.mean()) if len(y) else float("nan"),
                "query_images": len(np.unique(groups[sel])),
                "positive_images": pos_images,
                "positive_images_needed": min_positive_images,
                "verdict": chance.verdict(ap, floor[1], floor[2], nan, nan, evidence),
            }
        )
    return rows


def pooled_rows(
    cfg: EvalSettings,
    samples: pd.DataFrame,
    methods: tuple[str, ...],
    split: Split,
    table: str,
    ids: dict[str, int],
    keep: dict[tuple[str, str, str], np.ndarray] | None = None,
) -> list[dict]:
    """Table I (``table = "I"``) or S (``"S"``) column ``split``, all proposals and season pairs.

    ``keep`` receives each method's bootstrap APs by (table, split, method) (Table L's paired
    differences between localizers use the same resamples).
    """
    df = samples
    names = sample_groups(df)
    gi = np.array([ids[g] for g in names], np.int64)
    roc, sob = df["RoC"].to_numpy(), df["SoB"].to_numpy()
    lab = split_label(roc, sob, split) if table == "I" else stratified_labels(roc, split)
    edges = np.asarray(cfg.splits.sob_strata, np.float64)
    pooled = Pooled(cfg, ids, f"{table}:{split.name}")
    for m in methods:
        loc = df[f"loc_{m}"].to_numpy()
        sel = (lab >= 0) & ~np.isnan(loc)
        y, sc, g, sb = lab[sel] == 1, loc[sel], gi[sel], sob[sel]
        pos_frames = query_frames(names[sel][y])
        draws = cfg.report.chance_draws
        if table == "I":
            ap, floor = average_precision(y, sc), chance.plain_chance(y, draws, cfg.seed)
            boot = partial(bootstrap_aps, y, sc, g)
        else:
            ap = stratified_ap(y, sc, sb, edges)[0]
            floor = chance.stratified_chance(y, sb, edges, draws, cfg.seed)
            boot = partial(bootstrap_aps, y, sc, g, strata=(sb, edges))

        pooled.add(
            m,
            {
                "table": table,
                "split": split.name,
                "roc_max": split.roc_max,
                "proposal_method": "all",
                "season_pair": "all",
                "ap": ap,
                **chance_fields(floor, ap),
                "positives": int(y.sum()),
                "negatives": int((~y).sum()),
                "left_out": int(((lab < 0) & ~np.isnan(loc)).sum()),
                "positive_rate": float(y.mean()) if len(y) else float("nan"),
                "query_images": len(np.unique(g)),
                "positive_images": pos_frames,
            },
            boot,
        )
    if keep is not None:
        keep.update({(table, split.name, m): b for m, b in pooled.boot.items()})
    return pooled.finish()

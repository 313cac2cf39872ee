"""Reports of a run (SPEC sections 6, 9 and 10).

Localization quality, Table I, the per-split reports and their summary, PR curves and LoC-map
figures.

Every file is written atomically; files of an earlier run into the same directory that this run
no longer produces (a split dropped from the config, an old figure) are removed, so a directory
never mixes two runs' reports.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .annotations import change_boxes
from .cache import write_parquet, write_text
from .config import Config
from .fusion import pixel_regions
from .methods import BASELINES, FUSION_METHODS, METHOD_LABELS, ordered_methods
from .metrics import (
    average_precision,
    bootstrap_aps,
    interval,
    paired_difference,
    pr_curve,
    resample_counts,
    stratified_ap,
    weighted_average_precision,
)
from .splits import Split, paper_splits, roc_sob
from .splits import label as split_label
from .texfmt import tex_escape as _tex_escape

log = logging.getLogger(__name__)


#: A query subimage is "clean" for the localization table when at most this share of it changed.
CLEAN_ROC = 0.05


def _fmt(v: float, digits: int = 2) -> str:
    return "NaN" if v != v else f"{v:.{digits}f}"


# ------------------------------------------------------------------ localization quality


def localization_table(
    ranks: pd.DataFrame, frames: pd.DataFrame, ann: pd.DataFrame
) -> pd.DataFrame:
    """Recall@1, recall@5 and median r per proposal method x season pair (and over all pairs).

    Each statistic is given over all ranked query subimages and over the clean ones (annotated
    query frames, RoC <= 0.05), next to its chance level: the mean of 1/L (recall@1 of a random
    ranking) and 0.5 (its median r).
    """
    cb = change_boxes(ann)
    size = {
        k: (int(w), int(h))
        for k, w, h in zip(
            frames[["session", "camera", "utime"]].itertuples(index=False, name=None),
            frames["width"],
            frames["height"],
            strict=True,
        )
    }
    roc = np.full(len(ranks), np.nan)
    for key, idx in ranks.groupby(["q_session", "q_camera", "q_utime"], sort=False).indices.items():
        k = (str(key[0]), str(key[1]), int(key[2]))
        if k in cb:
            w, h = size[k]
            roc[idx] = roc_sob(
                ranks[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)[idx], cb[k], w, h
            )[0]
    df = ranks.assign(_clean=roc <= CLEAN_ROC)
    rows = []
    for prop, gp in [("all", df), *df.groupby("method", sort=True)]:
        for pair, g in [("all", gp), *gp.groupby("season_pair", sort=True)]:
            c = g[g["_clean"]]
            rows.append(
                {
                    "proposals": str(prop),
                    "season_pair": str(pair),
                    "subimages": len(g),
                    "recall_at_1": float((g["rank"] == 1).mean()),
                    "recall_at_5": float((g["rank"] <= 5).mean()),
                    "median_r": float(g["r"].median()),
                    "chance_recall_at_1": float((1.0 / g["L"]).mean()),
                    "clean_subimages": len(c),
                    "clean_recall_at_1": float((c["rank"] == 1).mean()) if len(c) else float("nan"),
                    "clean_recall_at_5": float((c["rank"] <= 5).mean()) if len(c) else float("nan"),
                    "clean_median_r": float(c["r"].median()) if len(c) else float("nan"),
                    "median_place_size": float(g["place_size"].median())
                    if "place_size" in g.columns
                    else 1.0,
                }
            )
    return pd.DataFrame(rows)


LOC_COLUMNS = [
    ("subimages", "n", 0),
    ("recall_at_1", "R@1", 2),
    ("recall_at_5", "R@5", 2),
    ("median_r", "med r", 3),
    ("chance_recall_at_1", "chance R@1", 3),
    ("clean_recall_at_1", "clean R@1", 2),
    ("clean_recall_at_5", "clean R@5", 2),
    ("clean_median_r", "clean med r", 3),
]


def heading_suffix(localizer: str) -> str:
    """What every table heading adds: the localizer it measured (SPEC section 11)."""
    return f" (localizer: {localizer})" if localizer else ""


def localization_markdown(loc: pd.DataFrame, gt_radius_m: float, localizer: str = "") -> str:
    """The localization table as markdown (recall@1/5, median r, chance rates)."""
    head = (
        "| proposals | season pair | "
        + " | ".join(lab for _, lab, _ in LOC_COLUMNS)
        + " |\n|---|---|"
        + "---:|" * len(LOC_COLUMNS)
        + "\n"
    )
    body = "".join(
        f"| {r.proposals} | {r.season_pair} | "
        + " | ".join(
            str(int(getattr(r, c))) if d == 0 else _fmt(float(getattr(r, c)), d)
            for c, _, d in LOC_COLUMNS
        )
        + " |\n"
        for r in loc.itertuples(index=False)
    )
    foot = (
        "\nLocalization quality of the engines whose ranks every change figure rests on. "
        "Ground truth: the place of "
        f"the reference frame (frames within {gt_radius_m:g} m, SPEC section 6). R@k: share "
        "of query subimages whose "
        "place ranks within the first k; median r: median normalised rank (0.5 = chance); "
        "clean: subimages of "
        f"annotated frames with RoC <= {CLEAN_ROC}. R@1 by chance: mean 1/L.\n"
    )
    return f"# Localization quality{heading_suffix(localizer)}\n\n" + head + body + foot


# ------------------------------------------------------------------ change tables (I, S, P)

# : A baseline within this of the best of the six methods is reported under the table (SPEC section
# 7).
WARN_MARGIN = 0.02


def _groups(df: pd.DataFrame) -> np.ndarray:
    return (
        df["q_session"].astype(str)
        + "|"
        + df["q_camera"].astype(str)
        + "|"
        + df["q_utime"].astype(str)
        + "|"
        + df["r_session"].astype(str)
    ).to_numpy()


def stratified_labels(roc: np.ndarray, split: Split) -> np.ndarray:
    """SPEC section 8's size-stratified labels.

    By RoC only (+1 positive, 0 negative, -1 left out).
    """
    pos = (roc >= split.pos_roc[0]) & (roc <= split.pos_roc[1])
    neg = (roc >= split.neg_roc[0]) & (roc <= split.neg_roc[1])
    out = np.full(len(roc), -1, np.int8)
    out[neg] = 0
    out[pos] = 1
    return out


class _Pooled:
    """Pooled APs of one table column for every method, with bootstrap intervals.

    Also the paired comparison with ``rank_fusion`` over the same resampled query images.
    """

    def __init__(self, cfg: Config, image_ids: dict[str, int], column: str) -> None:
        self.cfg, self.ids, self.column = cfg, image_ids, column
        self.counts = resample_counts(
            len(image_ids), cfg.report.bootstrap, cfg.seed + (zlib.crc32(column.encode()) % 10_000)
        )
        self.rows: list[dict] = []
        self.boot: dict[str, np.ndarray] = {}

    def add(
        self, method: str, row: dict, boot_fn: Callable[[np.ndarray], np.ndarray] | None
    ) -> None:
        """``boot_fn(counts)`` gives the method's AP in every resample (None: no interval)."""
        b = boot_fn(self.counts) if boot_fn is not None and len(self.counts) else np.full(0, np.nan)
        lo, hi = interval(b, self.cfg.report.ci)
        self.boot[method] = b
        self.rows.append({**row, "method": method, "ci_low": lo, "ci_high": hi})

    def finish(self) -> list[dict]:
        ref = next((r for r in self.rows if r["method"] == "rank_fusion"), None)
        for r in self.rows:
            if ref is None or r["method"] == "rank_fusion" or not len(self.boot[r["method"]]):
                r.update(
                    {
                        "diff": float("nan"),
                        "diff_ci_low": float("nan"),
                        "diff_ci_high": float("nan"),
                        "sign_flip_share": float("nan"),
                    }
                )
            else:
                r.update(
                    paired_difference(
                        self.boot[r["method"]],
                        self.boot["rank_fusion"],
                        r["ap"],
                        ref["ap"],
                        self.cfg.report.ci,
                    )
                )
        return self.rows


def _table_i_rows(
    df: pd.DataFrame, split: Split, methods: tuple[str, ...], season_pair: str, proposals: str
) -> list[dict]:
    """Per-split APs without intervals (the breakdowns by proposal method and season pair)."""
    rows = []
    lab = split_label(df["RoC"].to_numpy(), df["SoB"].to_numpy(), split)
    groups = _groups(df)
    for m in methods:
        loc = df[f"loc_{m}"].to_numpy()
        sel = (lab >= 0) & ~np.isnan(loc)
        y = lab[sel] == 1
        rows.append(
            {
                "table": "I",
                "split": split.name,
                "roc_max": split.roc_max,
                "proposals": proposals,
                "season_pair": season_pair,
                "method": m,
                "ap": average_precision(y, loc[sel]),
                "floor": float(y.mean()) if len(y) else float("nan"),
                "ci_low": float("nan"),
                "ci_high": float("nan"),
                "positives": int(y.sum()),
                "negatives": int((~y).sum()),
                "left_out": int(((lab < 0) & ~np.isnan(loc)).sum()),
                "positive_rate": float(y.mean()) if len(y) else float("nan"),
                "query_images": len(np.unique(groups[sel])),
            }
        )
    return rows


def _pooled_rows(
    cfg: Config,
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
    gi = np.array([ids[g] for g in _groups(df)], np.int64)
    roc, sob = df["RoC"].to_numpy(), df["SoB"].to_numpy()
    lab = split_label(roc, sob, split) if table == "I" else stratified_labels(roc, split)
    edges = np.asarray(cfg.splits.sob_strata, np.float64)
    pooled = _Pooled(cfg, ids, f"{table}:{split.name}")
    for m in methods:
        loc = df[f"loc_{m}"].to_numpy()
        sel = (lab >= 0) & ~np.isnan(loc)
        y, sc, g, sb = lab[sel] == 1, loc[sel], gi[sel], sob[sel]
        if table == "I":
            ap, floor = average_precision(y, sc), (float(y.mean()) if len(y) else float("nan"))

            boot = partial(bootstrap_aps, y, sc, g)
        else:
            ap, floor = stratified_ap(y, sc, sb, edges)

            boot = partial(bootstrap_aps, y, sc, g, stat="stratified", sob=sb, edges=edges)

        pooled.add(
            m,
            {
                "table": table,
                "split": split.name,
                "roc_max": split.roc_max,
                "proposals": "all",
                "season_pair": "all",
                "ap": ap,
                "floor": floor,
                "positives": int(y.sum()),
                "negatives": int((~y).sum()),
                "left_out": int(((lab < 0) & ~np.isnan(loc)).sum()),
                "positive_rate": float(y.mean()) if len(y) else float("nan"),
                "query_images": len(np.unique(g)),
            },
            boot,
        )
    if keep is not None:
        keep.update({(table, split.name, m): b for m, b in pooled.boot.items()})
    return pooled.finish()


def _pixel_image_rows(
    cfg: Config,
    samples: pd.DataFrame,
    frames: pd.DataFrame,
    ann: pd.DataFrame,
    methods: tuple[str, ...],
    ids: dict[str, int],
) -> list[dict]:
    """Table P (SPEC section 9).

    Pixel AP over exact regions and image AP, pooled, with intervals.
    """
    cb = change_boxes(ann)
    size = {
        k: (float(w), float(h))
        for k, w, h in zip(
            frames[["session", "camera", "utime"]].itertuples(index=False, name=None),
            frames["width"],
            frames["height"],
            strict=True,
        )
    }
    low = {
        m: float(np.nanmin(samples[f"loc_{m}"].to_numpy()))
        if samples[f"loc_{m}"].notna().any()
        else 0.0
        for m in methods
    }
    px: dict[str, dict[str, list]] = {m: {"s": [], "y": [], "w": [], "g": []} for m in methods}
    img: dict[str, dict[str, list]] = {m: {"s": [], "y": [], "g": []} for m in methods}
    groups = _groups(samples)
    boxes = samples[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    locs = {m: samples[f"loc_{m}"].to_numpy(np.float64) for m in methods}
    fused_methods = [m for m in methods if m != "rank_no_fusion"]
    in_fused = (
        np.isfinite(np.column_stack([locs[m] for m in fused_methods])).any(1)
        if fused_methods
        else np.zeros(len(samples), bool)
    )
    qs, qc, qu = (
        samples["q_session"].to_numpy(),
        samples["q_camera"].to_numpy(),
        samples["q_utime"].to_numpy(),
    )
    for gkey, idx in pd.Series(np.arange(len(samples))).groupby(groups, sort=True).indices.items():
        qk = (str(qs[idx[0]]), str(qc[idx[0]]), int(qu[idx[0]]))
        w, h = size[qk]
        change = cb.get(qk, np.zeros((0, 4)))
        gid = ids[gkey]
        sets = {"fused": idx[in_fused[idx]]}
        if "rank_no_fusion" in methods:
            o = idx[np.isfinite(locs["rank_no_fusion"][idx])]
            sets["orig"] = o[
                np.argsort(-locs["rank_no_fusion"][o], kind="stable")
            ]  # identical boxes: the highest LoC owns their regions
        regions = {}
        for k, v in sets.items():
            area, pos, owner = pixel_regions(boxes[v], change, w, h)
            # regions with the same owner and label get the same LoC under every method: sum them
            # once
            uniq, inv = np.unique((owner + 1) * 2 + pos, return_inverse=True)
            regions[k] = (np.bincount(inv, weights=area), (uniq % 2).astype(bool), uniq // 2 - 1)
        for m in methods:
            key = "orig" if m == "rank_no_fusion" else "fused"
            area, pos, owner = regions[key]
            vals = locs[m][sets[key]]
            px[m]["s"].append(
                np.where(owner >= 0, vals[np.maximum(owner, 0)] if len(vals) else low[m], low[m])
            )
            px[m]["y"].append(pos)
            px[m]["w"].append(area)
            px[m]["g"].append(np.full(len(area), gid))
            v = locs[m][idx]
            if np.isfinite(v).any():
                img[m]["s"].append(float(np.nanmax(v)))
                img[m]["y"].append(bool(len(change)))
                img[m]["g"].append(gid)
    rows = []
    for name, data in (("pixel", px), ("image", img)):
        pooled = _Pooled(cfg, ids, f"P:{name}")
        for m in methods:
            d = data[m]
            if name == "pixel":
                s_ = np.concatenate(d["s"]) if d["s"] else np.zeros(0)
                y_ = np.concatenate(d["y"]).astype(bool) if d["y"] else np.zeros(0, bool)
                w_ = np.concatenate(d["w"]) if d["w"] else np.zeros(0)
                g_ = np.concatenate(d["g"]) if d["g"] else np.zeros(0, np.int64)
                ap = weighted_average_precision(y_, s_, w_)
                pos_w, tot_w = float(w_[y_].sum()), float(w_.sum())

                boot = partial(bootstrap_aps, y_, s_, g_, weights=w_)

                extra = {
                    "positives": round(pos_w),
                    "negatives": round(tot_w - pos_w),
                    "positive_rate": pos_w / tot_w if tot_w else float("nan"),
                }
            else:
                s_, y_, g_ = (
                    np.asarray(d["s"], np.float64),
                    np.asarray(d["y"], bool),
                    np.asarray(d["g"], np.int64),
                )
                ap = average_precision(y_, s_)

                boot = partial(bootstrap_aps, y_, s_, g_)

                extra = {
                    "positives": int(y_.sum()),
                    "negatives": int((~y_).sum()),
                    "positive_rate": float(y_.mean()) if len(y_) else float("nan"),
                }
            pooled.add(
                m,
                {
                    "table": "P",
                    "split": name,
                    "roc_max": float("nan"),
                    "proposals": "all",
                    "season_pair": "all",
                    "ap": ap,
                    "floor": extra["positive_rate"],
                    "left_out": 0,
                    "query_images": len(np.unique(g_)),
                    **extra,
                },
                boot,
            )
        rows += pooled.finish()
    return rows


def confound_warnings(main: pd.DataFrame, table: str) -> list[str]:
    """SPEC section 7: warn where a baseline that reads no pixel nears the best method.

    Where one comes within 0.02 of the best of the six methods, say so: one line per baseline,
    naming every split where it happens and both APs.
    """
    hits: dict[str, list[str]] = {}
    for split, g in main.groupby("split", sort=False):
        six = g[g["method"].isin(FUSION_METHODS)].dropna(subset=["ap"])
        if not len(six):
            continue
        best = six.loc[six["ap"].idxmax()]
        for b in BASELINES:
            row = g[g["method"] == b]
            if (
                len(row)
                and np.isfinite(row["ap"].iloc[0])
                and row["ap"].iloc[0] >= best["ap"] - WARN_MARGIN
            ):
                name = (
                    f"RoC-max {row['roc_max'].iloc[0]:.2f}" if table != "Table P" else f"{split} AP"
                )
                hits.setdefault(b, []).append(
                    f"{name}: {row['ap'].iloc[0]:.2f} vs {best['method']} {best['ap']:.2f}"
                )
    see = (
        "; read Table S (tableS.md), which compares boxes of the same size"
        if table == "Table I"
        else ""
    )
    return [
        f"WARNING ({table}): the baseline {b}, which reads no pixel, comes within "
        f"{WARN_MARGIN} of the best of the six methods "
        f"({'; '.join(v)}): under this protocol it separates the labels without detecting "
        f"anything{see}."
        for b, v in hits.items()
    ]


# ------------------------------------------------------------------ rendering


def pivot(
    summ: pd.DataFrame, table: str, methods: tuple[str, ...], value: str = "ap"
) -> pd.DataFrame:
    """One table's ``value`` (AP by default), method x split, in SPEC order."""
    main = summ[
        (summ["table"] == table) & (summ["proposals"] == "all") & (summ["season_pair"] == "all")
    ]
    col = "split" if table == "P" else "roc_max"
    t = main.pivot(index="method", columns=col, values=value).reindex(list(methods))
    if table == "P":
        t = t.reindex(columns=["pixel", "image"])
    return t


def table_csv(table: pd.DataFrame, localizer: str | None = None, header: bool = True) -> str:
    """One row per method id (first column ``method``), one column per split, two decimals.

    With ``localizer`` a first column names it (a run of several localizers: one CSV, a block of
    rows each; ``header`` only on the first).
    """
    pre = "" if localizer is None else "localizer,"
    lines = [pre + "method," + ",".join(_col(c) for c in table.columns)] if header else []
    cell = "" if localizer is None else (f'"{localizer}",' if "," in localizer else f"{localizer},")
    for m, row in table.iterrows():
        lines.append(
            cell
            + str(m)
            + ","
            + ",".join("nan" if np.isnan(v) else f"{v:.2f}" for v in row.to_numpy())
        )
    return "\n".join(lines) + "\n"


def _col(c: Any) -> str:
    return f"{c:.2f}" if isinstance(c, float) else str(c)


def _cell(v: float, lo: float, hi: float) -> str:
    if v != v:
        return "NaN"
    return f"{v:.2f} [{lo:.2f}, {hi:.2f}]" if lo == lo else f"{v:.2f}"


TABLE_INTRO = {
    "I": (
        "Table I",
        (
            "AP by RoC-max of the negative range, the paper's protocol (SPEC section 8): "
            "positives are small boxes "
            "(SoB <= 0.4), negatives large ones (SoB >= 0.4)."
        ),
    ),
    "S": (
        "Table S",
        (
            "Size-stratified AP (SPEC section 8): labels by RoC only, AP within SoB strata of "
            "boxes of the same size, "
            "weighted by the strata's positives. The floor is the same weighted mean of the "
            "strata's positive rates."
        ),
    ),
    "P": (
        "Table P",
        (
            "Pixel AP (each pixel takes the LoC of the smallest sample box holding it; exact "
            "region areas) and image AP "
            "(each query image scores the largest LoC of its samples), SPEC section 9."
        ),
    ),
}


def table_markdown(
    summ: pd.DataFrame,
    table: str,
    methods: tuple[str, ...],
    warnings: list[str],
    localizer: str = "",
) -> str:
    """A change table as markdown: the six methods, then the variants and baselines.

    Cells AP [95% interval].
    """
    ap, lo, hi = (pivot(summ, table, methods, v) for v in ("ap", "ci_low", "ci_high"))
    floor = pivot(summ, table, methods, "floor")
    cols = list(ap.columns)
    title, intro = TABLE_INTRO[table]
    head = (
        "| AP [95% CI] | "
        + " | ".join(_col(c) for c in cols)
        + " |\n|---|"
        + "---:|" * len(cols)
        + "\n"
    )
    lines, first_extra = [], True
    for m in ap.index:
        if m not in FUSION_METHODS and first_extra:
            lines.append("| *variants and baselines* |" + " |" * len(cols) + "\n")
            first_extra = False
        lines.append(
            f"| {METHOD_LABELS[str(m)]} | "
            + " | ".join(_cell(ap.loc[m, c], lo.loc[m, c], hi.loc[m, c]) for c in cols)
            + " |\n"
        )
    ref = next((m for m in ("rank_fusion", "score_max") if m in floor.index), floor.index[0])
    lines.append(
        f"| *floor ({'fused set' if ref != 'rank_no_fusion' else 'original boxes'})* | "
        + " | ".join(_fmt(floor.loc[ref, c]) for c in cols)
        + " |\n"
    )
    if "rank_no_fusion" in floor.index and table != "P":
        lines.append(
            "| *floor (original boxes)* | "
            + " | ".join(_fmt(floor.loc["rank_no_fusion", c]) for c in cols)
            + " |\n"
        )
    main = summ[
        (summ["table"] == table)
        & (summ["proposals"] == "all")
        & (summ["season_pair"] == "all")
        & (summ["method"] == ref)
    ]
    counts = "; ".join(
        f"{_col(r.roc_max if table != 'P' else r.split)}: {r.positives} positives / "
        f"{r.negatives} negatives" + (" (pixels)" if table == "P" and r.split == "pixel" else "")
        for r in main.itertuples()
    )
    warn = "".join(f"\n**{w}**\n" for w in warnings)
    return (
        f"# {title}{heading_suffix(localizer)}\n\n{intro}\n\n"
        + head
        + "".join(lines)
        + f"\nFloor: the AP of a random ranking. Counts ({ref}): {counts}. Intervals: 95% "
        "bootstrap over query images; "
        "the paired differences with rank fusion are in comparisons.md.\n" + warn
    )


def table_latex(t: pd.DataFrame, caption_cols: str = "", localizer: str = "") -> str:
    """A booktabs ``tabular`` of one table.

    Two decimals; the variants and baselines come after a rule. The localizer is named in a
    comment line above it.
    """
    cols = list(t.columns)
    out = [f"% localizer: {localizer}"] if localizer else []
    out += [
        r"\begin{tabular}{l" + "r" * len(cols) + "}",
        r"\toprule",
        " & ".join([_tex_escape(caption_cols or "Method")] + [_tex_escape(_col(c)) for c in cols])
        + r" \\",
        r"\midrule",
    ]
    first_extra = True
    for m, row in t.iterrows():
        if m not in FUSION_METHODS and first_extra and m in METHOD_LABELS:
            out.append(r"\midrule")
            first_extra = False
        label = METHOD_LABELS.get(str(m), str(m))
        out.append(
            " & ".join(
                [_tex_escape(label)] + ["--" if v != v else f"{v:.2f}" for v in row.to_numpy()]
            )
            + r" \\"
        )
    out += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(out) + "\n"


def comparisons_markdown(summ: pd.DataFrame, methods: tuple[str, ...], localizer: str = "") -> str:
    """Every method against rank fusion, in words, for every pooled column of Tables I, S and P."""
    lines = [
        f"# Paired comparisons with rank fusion{heading_suffix(localizer)}",
        "",
        (
            "Each line: AP(method) - AP(rank fusion) [95% interval of the difference over the "
            "same bootstrap resamples of query "
            "images]; 'sign flips' is the share of resamples in which the difference has the "
            "other sign."
        ),
        "",
    ]
    for table in ("I", "S", "P"):
        main = summ[
            (summ["table"] == table) & (summ["proposals"] == "all") & (summ["season_pair"] == "all")
        ]
        for split, g in main.groupby("split", sort=False):
            lines.append(f"## {TABLE_INTRO[table][0]}, {split}")
            lines.append("")
            for r in g.itertuples():
                if r.method == "rank_fusion" or r.diff != r.diff:
                    continue
                flips = (
                    f"sign flips in {100 * r.sign_flip_share:.0f}% of resamples"
                    if r.sign_flip_share == r.sign_flip_share
                    else "no difference"
                )
                lines.append(
                    f"- {METHOD_LABELS[r.method]} - rank fusion = {r.diff:+.2f} "
                    f"[{r.diff_ci_low:+.2f}, {r.diff_ci_high:+.2f}] ({flips})"
                )
            lines.append("")
    return "\n".join(lines)


def localization_latex(loc: pd.DataFrame, localizer: str = "") -> str:
    """The localization table (all season pairs) as a booktabs ``tabular``."""
    t = loc[loc["season_pair"] == "all"].set_index("proposals")[
        ["recall_at_1", "recall_at_5", "median_r", "chance_recall_at_1", "clean_recall_at_1"]
    ]
    t.columns = ["R@1", "R@5", "median r", "R@1 by chance", "clean R@1"]
    return table_latex(t, "Proposals", localizer)


# ------------------------------------------------------------------ all reports


def _remove_stale(directory: Path, pattern: str, keep: set[Path]) -> int:
    """Remove files matching ``pattern`` in ``directory`` that are not in ``keep``.

    ``directory`` lies inside the harness's own run directory.
    """
    n = 0
    if directory.is_dir():
        for p in directory.glob(pattern):
            if p.is_file() and p.resolve() not in keep:
                p.unlink()
                n += 1
    return n


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


def write_reports(
    cfg: Config,
    out: Path,
    samples: pd.DataFrame | Sequence[Block],
    ranks: pd.DataFrame | None = None,
    frames: pd.DataFrame | None = None,
    ann: pd.DataFrame | None = None,
    progress: Callable[[Iterable[Any]], Iterable[Any]] = lambda it: it,
    localizer: str = "",
    notes: Sequence[str] = (),
) -> Reports:
    """Write every report of a run into ``out``.

    ``samples`` is one localizer's sample table (with ``ranks``, ``localizer`` and ``notes``), or
    a list of :class:`Block` (SPEC section 11: one per localizer, then ``all localizers``). A
    localizer is named in every heading and in a ``localizer`` column of the split reports and
    the summary; ``notes`` are printed under every change table. With one block the files are
    those of a one-localizer run; with several, each CSV gains a ``localizer`` column, each
    markdown/LaTeX file a section per block, and Table L (``tableL.*``) is written.
    """
    assert frames is not None and ann is not None
    if isinstance(samples, pd.DataFrame):
        assert ranks is not None
        blocks = [
            Block(localizer, samples, ranks, ordered_methods(cfg.fusion.methods), list(notes))
        ]
    else:
        blocks = list(samples)
    multi = len(blocks) > 1
    written: set[Path] = set()

    def put(path: Path) -> Path:
        written.add(path.resolve())
        return path

    def tag(df: pd.DataFrame, name: str) -> pd.DataFrame:
        if multi and "localizer" not in df.columns:
            df = df.copy()
            df.insert(0, "localizer", name)
        return df

    located = [b for b in blocks if b.ranks is not None]
    locs = {
        b.name: localization_table(b.ranks, frames, ann) for b in located if b.ranks is not None
    }
    write_text(
        put(out / "localization.csv"),
        pd.concat([tag(v, k) for k, v in locs.items()], ignore_index=True).to_csv(
            index=False, float_format="%.4f"
        ),
    )
    write_text(
        put(out / "localization.md"),
        "\n".join(localization_markdown(v, cfg.retrieval.gt_radius_m, k) for k, v in locs.items()),
    )
    write_text(
        put(out / "localization.tex"),
        "\n".join(localization_latex(v, k) for k, v in locs.items()),
    )
    write_parquet(
        put(out / "ranks.parquet"),
        pd.concat([b.ranks.assign(localizer=b.name) for b in located if b.ranks is not None]),
    )
    splits = paper_splits(cfg.splits)
    allps = [b.samples[b.samples["proposals"] == "all"].reset_index(drop=True) for b in blocks]
    ids = {g: i for i, g in enumerate(sorted(set().union(*(set(_groups(a)) for a in allps))))}
    summaries: list[list[dict]] = [[] for _ in blocks]
    curves: list[list[pd.DataFrame]] = [[] for _ in blocks]
    boots: list[dict[tuple[str, str, str], np.ndarray]] = [{} for _ in blocks]
    for sp in progress(splits):
        reps = []
        for bi, b in enumerate(blocks):
            rep = _split_block(cfg, b, allps[bi], sp, ids, summaries[bi], curves[bi], boots[bi])
            reps.append(rep)
        write_parquet(
            put(out / "splits" / f"{sp.name}.parquet"), pd.concat(reps, ignore_index=True)
        )
        del reps
    results = []
    for bi, b in enumerate(blocks):
        summaries[bi] += _pixel_image_rows(cfg, allps[bi], frames, ann, b.methods, ids)
        summ = pd.DataFrame(summaries[bi])
        summ.insert(0, "localizer", b.name)
        tables, warnings = {}, {}
        for table in ("I", "S", "P"):
            main = summ[
                (summ["table"] == table)
                & (summ["proposals"] == "all")
                & (summ["season_pair"] == "all")
            ]
            warnings[table] = confound_warnings(main, TABLE_INTRO[table][0]) + list(b.notes)
            tables[table] = pivot(summ, table, b.methods)
        loc_b = locs.get(b.name, pd.DataFrame())
        results.append(Reports(summ, loc_b, tables, warnings, b.methods, b.name))
    summ_all = pd.concat([r.summary for r in results], ignore_index=True)
    write_parquet(put(out / "splits" / "summary.parquet"), summ_all)
    allc = [
        tag(pd.concat(c, ignore_index=True), b.name)
        for b, c in zip(blocks, curves, strict=True)
        if c
    ]
    if allc:
        write_parquet(put(out / "splits" / "pr_curves.parquet"), pd.concat(allc, ignore_index=True))
    for table, stem in (("I", "table1"), ("S", "tableS"), ("P", "tableP")):
        write_text(
            put(out / f"{stem}.csv"),
            "".join(
                table_csv(r.tables[table], r.localizer if multi else None, header=i == 0)
                for i, r in enumerate(results)
            ),
        )
        write_text(
            put(out / f"{stem}.md"),
            "\n".join(
                table_markdown(r.summary, table, r.methods, r.warnings[table], r.localizer)
                for r in results
            ),
        )
        write_text(
            put(out / f"{stem}.tex"),
            "\n".join(
                table_latex(r.tables[table], "AP" if table != "P" else "Method", r.localizer)
                for r in results
            ),
        )
    table_l = None
    cmp_md = "\n".join(comparisons_markdown(r.summary, r.methods, r.localizer) for r in results)
    if multi:
        from .leaderboard import leaderboard, leaderboard_csv, leaderboard_latex, leaderboard_md

        table_l = leaderboard(cfg, results, boots, splits)
        write_text(put(out / "tableL.csv"), leaderboard_csv(table_l))
        write_text(put(out / "tableL.md"), leaderboard_md(table_l, cfg))
        write_text(put(out / "tableL.tex"), leaderboard_latex(table_l))
        cmp_md = leaderboard_md(table_l, cfg, comparisons=True) + "\n" + cmp_md
    write_text(put(out / "comparisons.md"), cmp_md)
    if cfg.report.plots:
        from .plots import locmap_figures, pr_plots

        if curves[0]:
            for png in pr_plots(pd.concat(curves[0], ignore_index=True), out / "plots"):
                put(png)
        for png in locmap_figures(
            blocks[0].samples, frames, ann, out / "locmaps", cfg.report.locmap_examples
        ):
            put(png)
    stale = _remove_stale(out / "splits", "*.parquet", written) + _remove_stale(
        out / "plots", "pr_*.png", written
    )
    stale += _remove_stale(out / "locmaps", "*", written)
    stale += _remove_stale(out, "tableL.*", written)
    if stale:
        log.info(
            "reports: removed %d file(s) of an earlier run that this run no longer writes", stale
        )
    if not multi:
        return results[0]
    first = results[0]
    return Reports(
        summ_all,
        pd.concat([tag(v, k) for k, v in locs.items()], ignore_index=True),
        first.tables,
        {
            t: [f"[{r.localizer}] {w}" for r in results for w in r.warnings[t]]
            for t in ("I", "S", "P")
        },
        first.methods,
        ", ".join(r.localizer for r in results),
        results,
        table_l,
    )


def _split_block(
    cfg: Config,
    b: Block,
    allp: pd.DataFrame,
    sp: Split,
    ids: dict[str, int],
    summary: list[dict],
    curves: list[pd.DataFrame],
    boots: dict[tuple[str, str, str], np.ndarray],
) -> pd.DataFrame:
    """One block's split report (returned) and its summary rows and PR curves (appended)."""
    samples, methods = b.samples, b.methods
    lab = split_label(samples["RoC"].to_numpy(), samples["SoB"].to_numpy(), sp)
    rep = samples.assign(
        label=lab, label_stratified=stratified_labels(samples["RoC"].to_numpy(), sp)
    )
    rep.insert(0, "localizer", b.name)
    summary += _pooled_rows(cfg, allp, methods, sp, "I", ids, boots)
    summary += _pooled_rows(cfg, allp, methods, sp, "S", ids, boots)
    for prop, g in samples.groupby("proposals", sort=True):
        if prop != "all":
            summary += _table_i_rows(g, sp, methods, "all", str(prop))
        else:
            for pair, gp in g.groupby("season_pair", sort=True):
                summary += _table_i_rows(gp, sp, methods, str(pair), "all")
    allg = rep[rep["proposals"] == "all"]
    for m in methods:
        sel = (allg["label"] >= 0) & allg[f"loc_{m}"].notna()
        if (allg.loc[sel, "label"] == 1).any():
            thr, p, r = pr_curve(
                allg.loc[sel, "label"].to_numpy() == 1, allg.loc[sel, f"loc_{m}"].to_numpy()
            )
            curves.append(
                pd.DataFrame(
                    {"split": sp.name, "method": m, "threshold": thr, "precision": p, "recall": r}
                )
            )
    return rep

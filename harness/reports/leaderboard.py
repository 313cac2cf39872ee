"""Table L, the leaderboard of localizers (SPEC section 11).

One row per localizer and one for ``all localizers`` (their boxes fused by rank): recall@N for
each N of ``[report] recall_at`` (undefined for the fused row), Table S ``rank_fusion`` and
``score_max`` at the headline RoC-max (``[report] headline_roc_max``), Table P pixel and image
AP of ``rank_fusion``, each AP with its 95% interval and floor, and each row's paired difference
from the first localizer in Table S ``rank_fusion`` over the same bootstrap resamples of query
images. Computed from the blocks' summaries (:func:`harness.reports.write.write_reports`), rendered
as CSV, markdown and LaTeX. Then what each localizer costs (:mod:`harness.runtime.costs`): bytes per
subimage, map storage per reference frame, encode and rank time, build time. An undefined cell
is ``-`` with its reason in a footnote (:func:`undefined`), in every rendering alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from harness.config.schema import Config
from harness.evaluate.chance import MARK_LEGEND, VERDICT_MARKS
from harness.evaluate.metrics import holm, paired_difference
from harness.evaluate.splits import Split
from harness.reports.texfmt import tex_escape as _tex_escape
from harness.runtime.costs import COST_COLUMNS, IMPORTED_WHY

#: (column prefix, table, split selector, method, heading) of Table L's AP columns.
AP_COLUMNS = (
    ("S_rank_fusion", "S", "headline", "rank_fusion", "Table S rank fusion"),
    ("S_score_max", "S", "headline", "score_max", "Table S score max"),
    ("P_pixel", "P", "pixel", "rank_fusion", "pixel AP (rank fusion)"),
    ("P_image", "P", "image", "rank_fusion", "image AP (rank fusion)"),
)


#: Footnote mark -> why a Table L cell is undefined (:func:`undefined`).
WHY = {
    "a": "the fused row ranks nothing itself: no recall of its own",
    "b": "scores of different localizers are not comparable: no score method across localizers",
    "c": "no positive sample in this split",
    "d": "the fused row keeps no descriptor of its own: its cost is its localizers' together",
    "e": IMPORTED_WHY,
    "f": "not measured in this run (its entries were built before costs were recorded)",
}


def recall_columns(t: pd.DataFrame) -> list[tuple[str, str]]:
    """(column, heading) of Table L's recall@N columns, N from ``[report] recall_at``."""
    ns = sorted(int(c[10:]) for c in t.columns if c.startswith("recall_at_") and c[10:].isdigit())
    return [(f"recall_at_{n}", f"R@{n}") for n in ns]


def undefined(t: pd.DataFrame, r: Any, column: str) -> str | None:
    """The footnote mark of a NaN cell of Table L (None where the cell has a value)."""
    v = r[column] if isinstance(r, pd.Series) else getattr(r, column)
    if v == v:
        return None
    fused = len(t) > 1 and str(r["localizer"] if isinstance(r, pd.Series) else r.localizer) == str(
        t["localizer"].iloc[-1]
    )
    if column.startswith("recall_at_"):
        return "a"
    if column in {c for c, *_ in COST_COLUMNS}:
        imported = bool(r["imported"] if isinstance(r, pd.Series) else r.imported)
        return "d" if fused else "e" if imported else "f"
    return "b" if fused else "c"


def headline_split(splits: Sequence[Split], roc_max: float) -> Split:
    """The split whose RoC-max is nearest the headline's (the first of equals)."""
    return min(splits, key=lambda s: abs(s.roc_max - roc_max))


def _cell(summ: pd.DataFrame, table: str, split: str, method: str) -> dict[str, Any]:
    r = summ[
        (summ["table"] == table)
        & (summ["split"] == split)
        & (summ["method"] == method)
        & (summ["proposals"] == "all")
        & (summ["season_pair"] == "all")
    ]
    if not len(r):
        nan = float("nan")
        return {
            **dict.fromkeys(("ap", "ci_low", "ci_high", "floor", "chance_high"), nan),
            "verdict": "undefined",
            "query_images": 0,
        }
    x = r.iloc[0]
    return {
        **{k: float(x[k]) for k in ("ap", "ci_low", "ci_high", "floor", "chance_high")},
        "verdict": str(x["verdict"]),
        "query_images": int(x["query_images"]),
    }


def leaderboard(
    cfg: Config,
    blocks: Sequence[Any],
    boots: Sequence[dict[tuple[str, str, str], np.ndarray]],
    splits: Sequence[Split],
) -> pd.DataFrame:
    """Table L: one row per block (localizers first, ``all localizers`` last).

    ``blocks`` are the blocks' :class:`harness.reports.write.Reports` (``summary``,
    ``localization``, ``localizer``).

    ``boots[i]`` holds block i's bootstrap APs by (table, split, method); the difference of each
    row from the first is paired over the same resamples (the blocks share the query images).
    """
    head = headline_split(splits, cfg.report.headline_roc_max)
    first = boots[0].get(("S", head.name, "rank_fusion"), np.zeros(0))
    rows: list[dict[str, Any]] = []
    for b, bt in zip(blocks, boots, strict=True):
        loc = b.localization
        la = loc[(loc["proposals"] == "all") & (loc["season_pair"] == "all")] if len(loc) else loc
        row: dict[str, Any] = {
            "localizer": b.localizer,
            "roc_max": head.roc_max,
            **{
                f"recall_at_{n}": float(la[f"recall_at_{n}"].iloc[0]) if len(la) else float("nan")
                for n in cfg.report.recall_at
            },
            "subimages": int(la["subimages"].iloc[0]) if len(la) else 0,
        }
        for prefix, table, split, method, _ in AP_COLUMNS:
            c = _cell(b.summary, table, head.name if split == "headline" else split, method)
            for k in ("ap", "ci_low", "ci_high", "floor", "chance_high", "verdict"):
                row[f"{prefix}_{k}"] = c[k]
            if prefix == "S_rank_fusion":
                row["query_images"] = c["query_images"]
        mine = bt.get(("S", head.name, "rank_fusion"), np.zeros(0))
        if rows and len(mine) and len(first) == len(mine):
            d = paired_difference(
                mine, first, row["S_rank_fusion_ap"], rows[0]["S_rank_fusion_ap"], cfg.report.ci
            )
        else:
            nan = float("nan")
            d = dict.fromkeys(
                ("diff", "diff_ci_low", "diff_ci_high", "sign_flip_share", "p_value"), nan
            )
        row.update({f"S_rank_fusion_{k}": v for k, v in d.items()})
        nan = float("nan")
        row.update({c: float(b.costs.get(c, nan)) for c, *_ in COST_COLUMNS})
        row["imported"] = bool(b.costs.get("imported", 0.0))
        rows.append(row)
    t = pd.DataFrame(rows)
    # the localizers' differences from the first are one family for Holm's correction
    t["S_rank_fusion_holm_survives"] = holm(
        t["S_rank_fusion_p_value"].to_numpy(np.float64), 1.0 - cfg.report.ci
    )
    return t


def leaderboard_csv(t: pd.DataFrame) -> str:
    """Table L as CSV: every column, four decimals."""
    out: str = t.to_csv(index=False, float_format="%.4f")
    return out


def _ap(r: Any, prefix: str) -> str:
    v, lo, hi, ver = (getattr(r, f"{prefix}_{k}") for k in ("ap", "ci_low", "ci_high", "verdict"))
    if v != v:
        return "-"
    mark = VERDICT_MARKS.get(str(ver), "")
    return (f"{v:.2f} [{lo:.2f}, {hi:.2f}]" if lo == lo else f"{v:.2f}") + (
        f" {mark}" if mark else ""
    )


def _pct(v: float) -> str:
    return "" if v != v else f"{v:.2f}"


def cost_text(v: float, digits: int) -> str:
    """A cost cell's number (bytes as an integer)."""
    return f"{v:,.0f}" if digits == 0 else f"{v:.{digits}f}"


def _footnotes(marks: set[str]) -> list[str]:
    return [f"{m}) -: {WHY[m]}." for m in sorted(marks)]


def leaderboard_comparisons_md(t: pd.DataFrame) -> str:
    """The differences between localizers in Table L, in words, with Holm's mark."""
    first = str(t["localizer"].iloc[0])
    roc = float(t["roc_max"].iloc[0])
    lines = [
        "# Paired comparisons between localizers (Table L)",
        "",
        f"Table S rank fusion at RoC-max {roc:.2f}: AP(localizer) - AP({first}) [95% "
        "interval over the same bootstrap resamples of query images].",
        "",
    ]
    tested = int(np.isfinite(t["S_rank_fusion_p_value"].to_numpy(np.float64)).sum())
    kept = int(t["S_rank_fusion_holm_survives"].sum())
    lines += [
        f"Table L: {kept} of the {tested} differences from {first} tested survive a Holm "
        f"correction over those {tested} (family-wise error 5%); they are marked [Holm].",
        "",
    ]
    for r in t.iloc[1:].itertuples():
        flips = (
            f"sign flips in {100 * r.S_rank_fusion_sign_flip_share:.0f}% of resamples"
            if r.S_rank_fusion_sign_flip_share == r.S_rank_fusion_sign_flip_share
            else "no difference"
        )
        p = r.S_rank_fusion_p_value
        ptxt = "" if p != p else ", p < 0.001" if p < 0.001 else f", p = {p:.3f}"
        lines.append(
            f"- {r.localizer} - {first} = {r.S_rank_fusion_diff:+.2f} "
            f"[{r.S_rank_fusion_diff_ci_low:+.2f}, {r.S_rank_fusion_diff_ci_high:+.2f}] "
            f"({flips}{ptxt})" + (" [Holm]" if r.S_rank_fusion_holm_survives else "")
        )
    return "\n".join(lines) + "\n"


def _floor_lines(t: pd.DataFrame, rec: list[tuple[str, str]]) -> list[str]:
    """Table L's floor row (the first localizer's) and the sentence on the other rows' floors."""
    first = str(t["localizer"].iloc[0])
    lines = []
    r0 = t.iloc[0]
    lines.append(
        f"| *floor ({first})* | "
        + " | " * len(rec)
        + " | ".join(_pct(float(r0[f"{p}_floor"])) for p, _, _, _, _ in AP_COLUMNS)
        + " | |"
    )
    other = [
        f"{r.localizer} {float(r.S_rank_fusion_floor):.2f}"
        for r in t.itertuples()
        if abs(float(r.S_rank_fusion_floor) - float(r0["S_rank_fusion_floor"])) >= 0.005
    ]
    lines.append("")
    lines.append(
        "Floor: the mean AP of random orders of the same samples (within the same strata, "
        "through the same pixel maps). "
        + (
            "Rows whose Table S floor differs (their boxes differ): " + ", ".join(other) + "."
            if other
            else "Every row's Table S floor is the same to two decimals."
        )
        + f" {MARK_LEGEND}"
    )
    return lines


def leaderboard_md(t: pd.DataFrame, cfg: Config, comparisons: bool = False) -> str:
    """Table L as markdown (``comparisons``: the differences between localizers, in words).

    The accuracy table, its floor and its footnotes; then the cost table
    (:mod:`harness.runtime.costs`) with the machine it was measured on.
    """
    first = str(t["localizer"].iloc[0])
    roc = float(t["roc_max"].iloc[0])
    if comparisons:
        return leaderboard_comparisons_md(t)
    heads = [h for _, _, _, _, h in AP_COLUMNS]
    rec = recall_columns(t)
    marks: set[str] = set()

    def dash(r: Any, column: str) -> str:
        m = undefined(t, r, column)
        assert m is not None
        marks.add(m)
        return f"-{m})"

    lines = [
        "# Table L: localizers",
        "",
        "One row per localizer and one for all localizers fused by rank (SPEC section 11). "
        f"Recall@N ({', '.join(h for _, h in rec)}) of the ground-truth place over every ranked "
        f"query subimage; AP [95% interval] of Table S at RoC-max {roc:.2f} and of Table P; the "
        f"last column is each row's Table S rank-fusion AP minus {first}'s, paired over the same "
        "bootstrap resamples of query images. Every localizer is scored on the same query "
        "images.",
        "",
        "| localizer | "
        + " | ".join(h for _, h in rec)
        + " | "
        + " | ".join(heads)
        + f" | Table S rank fusion - {first} |",
        "|---|" + "---:|" * (len(rec) + len(heads) + 1),
    ]
    for r in t.itertuples():
        diff = (
            ""
            if r.S_rank_fusion_diff != r.S_rank_fusion_diff
            else f"{r.S_rank_fusion_diff:+.2f} [{r.S_rank_fusion_diff_ci_low:+.2f}, "
            f"{r.S_rank_fusion_diff_ci_high:+.2f}]"
        )
        recs = [
            _pct(getattr(r, c)) if getattr(r, c) == getattr(r, c) else dash(r, c) for c, _ in rec
        ]
        aps = [
            _ap(r, p) if getattr(r, f"{p}_ap") == getattr(r, f"{p}_ap") else dash(r, f"{p}_ap")
            for p, _, _, _, _ in AP_COLUMNS
        ]
        lines.append(f"| {r.localizer} | " + " | ".join(recs + aps) + f" | {diff} |")
    lines += _floor_lines(t, rec)
    lines += ["", *_footnotes(marks)] if marks else []
    lines += ["", *cost_md(t)]
    return "\n".join(lines) + "\n"


def cost_md(t: pd.DataFrame) -> list[str]:
    """Table L's cost table as markdown lines (heading, table, footnotes, machine)."""
    marks: set[str] = set()
    lines = [
        "## What each localizer costs",
        "",
        "| localizer | " + " | ".join(h for _, h, _ in COST_COLUMNS) + " |",
        "|---|" + "---:|" * len(COST_COLUMNS),
    ]
    for r in t.itertuples():
        cells = []
        for c, _, d in COST_COLUMNS:
            v = float(getattr(r, c))
            if v == v:
                cells.append(cost_text(v, d))
            else:
                m = undefined(t, r, c)
                assert m is not None
                marks.add(m)
                cells.append(f"-{m})")
        lines.append(f"| {r.localizer} | " + " | ".join(cells) + " |")
    return [
        *lines,
        "",
        COST_NOTE,
        *(["", *_footnotes(marks)] if marks else []),
    ]


#: What the cost columns measure (under the cost table in every rendering).
COST_NOTE = (
    "Bytes per subimage and map KiB per reference frame: the descriptors a robot keeps (as "
    "stored by the run; bag-of-words vectors sparse). Encode ms per subimage: decoding, cropping "
    "and describing, over every subimage encoded; rank ms per query subimage: the engine's "
    "ranking of the place lists; build s: training or vocabulary. Times are this run's on the "
    "machine in run.json (costs.machine) and vary across machines; a cached entry keeps the time "
    "of the run that built it."
)


def leaderboard_latex(t: pd.DataFrame) -> str:
    """Table L as a booktabs ``tabular`` (APs with two decimals, no intervals; ``--`` undefined).

    Undefined cells carry their footnote mark, explained under the table.
    """
    rec = recall_columns(t)
    cols = [*(h for _, h in rec), *(h for _, _, _, _, h in AP_COLUMNS)]
    out = [
        r"\begin{tabular}{l" + "r" * len(cols) + "}",
        r"\toprule",
        " & ".join(["Localizer", *(_tex_escape(c) for c in cols)]) + r" \\",
        r"\midrule",
    ]
    marks: set[str] = set()

    def cell(r: Any, column: str) -> str:
        v = getattr(r, column)
        if v == v:
            return f"{v:.2f}"
        m = undefined(t, r, column)
        assert m is not None
        marks.add(m)
        return f"--$^{m}$"

    for r in t.itertuples():
        vals = [cell(r, c) for c, _ in rec] + [cell(r, f"{p}_ap") for p, *_ in AP_COLUMNS]
        out.append(" & ".join([_tex_escape(str(r.localizer)), *vals]) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}"]
    out += [rf"\par{{\footnotesize $^{m}$ --: {_tex_escape(WHY[m])}.}}" for m in sorted(marks)]
    return "\n".join(out) + "\n"

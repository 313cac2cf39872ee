"""Table L, the leaderboard of localizers (method §11).

One row per localizer and one for ``all localizers`` (their boxes fused by rank): recall@N for
each N of ``[report] recall_at`` (undefined for the fused row), Table S ``rank_fusion`` and
``score_max`` at the headline RoC-max (``[report] headline_roc_max``), Table P pixel and image
AP of ``rank_fusion``, each AP with its 95% interval and floor, and each row's paired difference
from the first localizer in Table S ``rank_fusion`` over the same bootstrap resamples of query
images. Computed from the blocks' summaries (:func:`harness.evaluate.leaderboard.leaderboard`),
rendered here as CSV, markdown and LaTeX. Then what each localizer costs
(:mod:`harness.runtime.costs`): bytes per subimage, map storage per reference frame, encode and
rank time, build time. An undefined cell is ``-`` with its reason in a footnote
(:func:`undefined`), in every rendering alike.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from harness.config.schema import Config
from harness.evaluate.chance import MARK_LEGEND, VERDICT_MARKS, few_text
from harness.evaluate.leaderboard import AP_COLUMNS
from harness.reports.texfmt import tex_escape as _tex_escape
from harness.runtime.costs import COST_COLUMNS, IMPORTED_WHY

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


def bound_name(name: str, share: float) -> str:
    """A Table L row's name, marked where its figures rest on bounds rather than ranks."""
    return f"{name} [bounds: {100 * share:.0f}%]" if share > 0 else name


def leaderboard_csv(t: pd.DataFrame) -> str:
    """Table L as CSV: every column, four decimals."""
    out: str = t.to_csv(index=False, float_format="%.4f")
    return out


@dataclass(frozen=True)
class LCell:
    """One cell of Table L: a value, or the footnote mark (``why``) saying why it is undefined.

    An AP has its interval, floor and verdict; a paired difference its interval and Holm's mark.
    """

    kind: str  # "num", "ap", "diff" or "cost"
    value: float
    low: float = float("nan")
    high: float = float("nan")
    floor: float = float("nan")
    verdict: str = ""
    holm: bool = False
    digits: int = 2
    why: str = ""
    #: An AP's query images holding a positive (said in a ``few`` cell, method §9).
    positive_images: int = 0

    def text(self) -> str:
        """The cell as the markdown and the console show it (``-<mark>)`` where undefined)."""
        if self.why:
            return f"-{self.why})"
        v, lo, hi = self.value, self.low, self.high
        if self.kind == "diff":
            return "" if v != v else f"{v:+.2f} [{lo:+.2f}, {hi:+.2f}]"
        if self.kind == "cost":
            return cost_text(v, self.digits)
        if self.kind == "num":
            return _pct(v)
        mark = VERDICT_MARKS.get(self.verdict, "")
        if self.verdict == "few":
            mark = few_text(self.positive_images)
        return (f"{v:.2f} [{lo:.2f}, {hi:.2f}]" if lo == lo else f"{v:.2f}") + (
            f" {mark}" if mark else ""
        )


@dataclass(frozen=True)
class LeaderTable:
    """Table L ready for any format: each localizer's cells, the floors and the cost table.

    Each row: recall, AP and paired-difference cells; ``floors``: the first localizer's;
    ``marks`` / ``cost_marks``: the footnotes the accuracy and cost tables use.
    """

    first: str
    roc_max: float
    recall_heads: tuple[str, ...]
    rows: tuple[tuple[str, tuple[LCell, ...]], ...]
    floors: tuple[float, ...]
    #: Rows whose Table S floor differs from the first's by 0.005 or more: "name 0.12".
    other_floors: tuple[str, ...]
    cost_rows: tuple[tuple[str, tuple[LCell, ...]], ...]
    marks: tuple[str, ...]
    cost_marks: tuple[str, ...]
    #: Per row computed on bounds (:func:`bound_name`): "name: n% of ... are bounds".
    bounds: tuple[str, ...] = ()

    @property
    def bounds_note(self) -> str:
        """The sentence under the table for rows marked ``[bounds: n%]`` (empty without one)."""
        if not self.bounds:
            return ""
        return (
            "[bounds: n%]: " + "; ".join(self.bounds) + ". An imported list truncated before "
            "the true place gives only a bound on its rank (method §12): that row's recall "
            "and APs are computed on bounds, not ranks, and are not comparable with the others."
        )

    @property
    def heads(self) -> tuple[str, ...]:
        """The accuracy table's headings after ``localizer``."""
        return (
            *self.recall_heads,
            *(h for *_, h in AP_COLUMNS),
            f"Table S rank fusion - {self.first}",
        )


def _undefined_cell(t: pd.DataFrame, r: pd.Series, column: str, kind: str) -> LCell:
    return LCell(kind, float("nan"), why=undefined(t, r, column) or "f")


def _accuracy_cells(t: pd.DataFrame, r: pd.Series, rec: list[tuple[str, str]]) -> list[LCell]:
    """One row's recall, AP and paired-difference cells."""
    cells = [
        LCell("num", float(r[c])) if r[c] == r[c] else _undefined_cell(t, r, c, "num")
        for c, _ in rec
    ]
    for p, *_ in AP_COLUMNS:
        v, lo, hi, fl = (float(r[f"{p}_{k}"]) for k in ("ap", "ci_low", "ci_high", "floor"))
        n = r.get(f"{p}_positive_images", 0)
        cells.append(
            LCell(
                "ap", v, lo, hi, fl, str(r[f"{p}_verdict"]), positive_images=int(n if n == n else 0)
            )
            if v == v
            else _undefined_cell(t, r, f"{p}_ap", "ap")
        )
    d, dl, dh = (float(r[f"S_rank_fusion_{k}"]) for k in ("diff", "diff_ci_low", "diff_ci_high"))
    holm_ok = bool(r.get("S_rank_fusion_holm_survives", False))
    cells.append(LCell("diff", d, dl, dh, holm=holm_ok))
    return cells


def leader_table(t: pd.DataFrame) -> LeaderTable:
    """Table L (:func:`leaderboard`'s frame, or ``tableL.csv`` read back) for every format."""
    first = str(t["localizer"].iloc[0])
    rec = recall_columns(t)
    rows, costs = [], []
    shares = t["bound_share"] if "bound_share" in t.columns else pd.Series(0.0, index=t.index)
    for (_, r), share in zip(t.iterrows(), shares, strict=True):
        name = bound_name(str(r["localizer"]), float(share))
        rows.append((name, tuple(_accuracy_cells(t, r, rec))))
        costs.append(
            (
                str(r["localizer"]),
                tuple(
                    LCell("cost", float(r[c]), digits=dg)
                    if r[c] == r[c]
                    else _undefined_cell(t, r, c, "cost")
                    for c, _, dg in COST_COLUMNS
                ),
            )
        )
    r0 = t.iloc[0]
    other = tuple(
        f"{r.localizer} {float(r.S_rank_fusion_floor):.2f}"
        for r in t.itertuples()
        if abs(float(r.S_rank_fusion_floor) - float(r0["S_rank_fusion_floor"])) >= 0.005
    )

    def used(rs: list) -> tuple[str, ...]:
        return tuple(sorted({c.why for _, cs in rs for c in cs if c.why}))

    bounds = tuple(
        f"{r['localizer']}: {100 * float(sh):.0f}% of its query subimages' ranks are bounds"
        for (_, r), sh in zip(t.iterrows(), shares, strict=True)
        if float(sh) > 0
    )

    return LeaderTable(
        first,
        float(t["roc_max"].iloc[0]),
        tuple(h for _, h in rec),
        tuple(rows),
        tuple(float(r0[f"{p}_floor"]) for p, *_ in AP_COLUMNS),
        other,
        tuple(costs),
        used(rows),
        used(costs),
        bounds,
    )


def _pct(v: float) -> str:
    return "" if v != v else f"{v:.2f}"


def cost_text(v: float, digits: int) -> str:
    """A cost cell's number (bytes as an integer)."""
    return f"{v:,.0f}" if digits == 0 else f"{v:.{digits}f}"


def _footnotes(marks: Iterable[str]) -> list[str]:
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


def _floor_lines(v: LeaderTable) -> list[str]:
    """Table L's floor row (the first localizer's) and the sentence on the other rows' floors."""
    lines = [
        f"| *floor ({v.first})* | "
        + " | " * len(v.recall_heads)
        + " | ".join(_pct(f) for f in v.floors)
        + " | |",
        "",
        "Floor: the mean AP of random orders of the same samples (within the same strata, "
        "through the same pixel maps). "
        + (
            "Rows whose Table S floor differs (their boxes differ): "
            + ", ".join(v.other_floors)
            + "."
            if v.other_floors
            else "Every row's Table S floor is the same to two decimals."
        )
        + f" {MARK_LEGEND}",
    ]
    return lines


def leaderboard_md(t: pd.DataFrame, cfg: Config, comparisons: bool = False) -> str:
    """Table L as markdown (``comparisons``: the differences between localizers, in words).

    The accuracy table, its floor and its footnotes; then the cost table
    (:mod:`harness.runtime.costs`) with the machine it was measured on.
    """
    if comparisons:
        return leaderboard_comparisons_md(t)
    v = leader_table(t)
    lines = [
        "# Table L: localizers",
        "",
        "One row per localizer and one for all localizers fused by rank (method §11). "
        f"Recall@N ({', '.join(v.recall_heads)}) of the ground-truth place over every ranked "
        f"query subimage; AP [95% interval] of Table S at RoC-max {v.roc_max:.2f} and of Table "
        f"P; the last column is each row's Table S rank-fusion AP minus {v.first}'s, paired over "
        "the same bootstrap resamples of query images. Every localizer is scored on the same "
        "query images.",
        "",
        "| localizer | " + " | ".join(v.heads) + " |",
        "|---|" + "---:|" * len(v.heads),
    ]
    lines += [f"| {name} | " + " | ".join(c.text() for c in cs) + " |" for name, cs in v.rows]
    lines += _floor_lines(v)
    lines += ["", f"**{v.bounds_note}**"] if v.bounds_note else []
    lines += ["", *_footnotes(v.marks)] if v.marks else []
    lines += ["", *cost_md(v)]
    return "\n".join(lines) + "\n"


def cost_md(v: LeaderTable) -> list[str]:
    """Table L's cost table as markdown lines (heading, table, footnotes, machine)."""
    return [
        "## What each localizer costs",
        "",
        "| localizer | " + " | ".join(h for _, h, _ in COST_COLUMNS) + " |",
        "|---|" + "---:|" * len(COST_COLUMNS),
        *(f"| {name} | " + " | ".join(c.text() for c in cs) + " |" for name, cs in v.cost_rows),
        "",
        COST_NOTE,
        *(["", *_footnotes(v.cost_marks)] if v.cost_marks else []),
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
    v = leader_table(t)
    cols = v.heads[:-1]
    out = [
        r"\begin{tabular}{l" + "r" * len(cols) + "}",
        r"\toprule",
        " & ".join(["Localizer", *(_tex_escape(c) for c in cols)]) + r" \\",
        r"\midrule",
    ]

    def cell(c: LCell) -> str:
        return f"--$^{c.why}$" if c.why else f"{c.value:.2f}"

    for name, cs in v.rows:
        out.append(" & ".join([_tex_escape(name), *(cell(c) for c in cs[:-1])]) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}"]
    out += [rf"\par{{\footnotesize $^{m}$ --: {_tex_escape(WHY[m])}.}}" for m in v.marks]
    if v.bounds_note:
        out.append(rf"\par{{\footnotesize {_tex_escape(v.bounds_note)}}}")
    return "\n".join(out) + "\n"

"""Tables I, S and P as specs (method §8-10): each built once from a run's summary.

A change table is a :class:`ChangeSpec` (what it is: title, intro, which summary column gives its
columns, what its floor is measured within, whether it has a ceiling) and, for one run, a
:class:`ChangeTable` (:func:`change_table`: its columns, a :class:`ChangeRow` per method with AP,
interval, floor and verdict per column, the chance rows of method §9, the counts, its notes and
warnings). Every format renders the ``ChangeTable``: the markdown, CSV and LaTeX
(:mod:`harness.reports.render`), the console (:mod:`harness.cli.console`) and the page
(:mod:`harness.reports.html.cells`); a row, a column, a chance row or a note of these tables is
added here, once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import pandas as pd

from harness.evaluate.chance import MIN_POSITIVE_IMAGES, VERDICT_MARKS, few_text, few_warning
from harness.methods import FUSION_METHODS, METHOD_LABELS, is_unfused, unfused


@dataclass(frozen=True)
class ChangeSpec:
    """What a change table is, apart from one run's numbers."""

    id: str
    #: Its files: ``<stem>.csv|md|tex``.
    stem: str
    title: str
    intro: str
    #: The console's title (the run and localizer follow in parentheses).
    caption: str
    #: The summary column whose values are the table's columns.
    column: str = "roc_max"
    #: A fixed order of the columns (else the summary's, sorted).
    order: tuple[str, ...] = ()
    #: Where the floor's random orders are drawn (after "random orders of the same samples").
    floor_within: str = ""
    #: The LaTeX table's corner cell.
    corner: str = "AP"
    #: Its chance rows add the ceiling (boxes scored by their RoC).
    ceiling: bool = False
    #: The count of each column is of pixels, for these columns.
    pixel_columns: tuple[str, ...] = ()
    #: On the page it sits in a collapsed section (a lower heading).
    collapsed: bool = False


#: The method's change tables, in the order they are written and shown.
CHANGE_TABLES: dict[str, ChangeSpec] = {
    "I": ChangeSpec(
        "I",
        "table1",
        "Table I",
        "AP by RoC-max of the negative range, the paper's protocol (method §8): "
        "positives are small boxes (SoB <= 0.4), negatives large ones (SoB >= 0.4).",
        "Table I: AP by RoC-max, the paper's protocol",
        collapsed=True,
    ),
    "S": ChangeSpec(
        "S",
        "tableS",
        "Table S",
        "Size-stratified AP (method §8): labels by RoC only, AP within SoB strata of "
        "boxes of the same size, weighted by the strata's positives. The floor is the mean of "
        "the same figure over random orders within the same strata (method §9).",
        "Table S: size-stratified AP by RoC-max",
        floor_within=" within the same strata",
    ),
    "P": ChangeSpec(
        "P",
        "tableP",
        "Table P",
        "Pixel AP (each pixel takes the LoC of the smallest sample box holding it; exact "
        "region areas) and image AP (each query image scores the largest LoC of its samples), "
        "method §9.",
        "Table P: pixel AP and image AP",
        column="split",
        order=("pixel", "image"),
        floor_within=" through the same pixel maps",
        corner="Method",
        ceiling=True,
        pixel_columns=("pixel",),
    ),
}


def pivot(
    summ: pd.DataFrame, table: str, methods: tuple[str, ...], value: str = "ap"
) -> pd.DataFrame:
    """One table's ``value`` (AP by default), method x column, in the method's order."""
    spec = CHANGE_TABLES[table]
    main = _pooled(summ, table)
    if value not in main.columns:  # a summary written before the column existed
        main = main.assign(**{value: float("nan")})
    t = main.pivot(index="fusion", columns=spec.column, values=value).reindex(list(methods))
    return t.reindex(columns=list(spec.order)) if spec.order else t


def _pooled(summ: pd.DataFrame, table: str) -> pd.DataFrame:
    """The table's pooled rows: every proposal method and season pair together."""
    return summ[
        (summ["table"] == table)
        & (summ["proposal_method"] == "all")
        & (summ["season_pair"] == "all")
    ]


def number(v: float, digits: int = 2) -> str:
    """``v`` to ``digits`` decimals; NaN as ``NaN``."""
    return "NaN" if v != v else f"{v:.{digits}f}"


def column_label(c: Any) -> str:
    """A table column's heading: a RoC-max to two decimals, a split by its name."""
    return f"{c:.2f}" if isinstance(c, float) else str(c)


def ap_cell(v: float, lo: float, hi: float, verdict: str = "", positive_images: float = 0) -> str:
    """An AP cell as text: ``AP [interval] mark`` (the verdict's mark), ``NaN`` where undefined.

    A ``few`` verdict shows no mark but ``too few positives (n)`` (method §9).
    """
    if v != v:
        return "NaN"
    mark = VERDICT_MARKS.get(verdict, "")
    if verdict == "few":
        mark = few_text(int(positive_images))
    return (f"{v:.2f} [{lo:.2f}, {hi:.2f}]" if lo == lo else f"{v:.2f}") + (
        f" {mark}" if mark else ""
    )


@dataclass(frozen=True)
class ChangeRow:
    """One fusion rule's line of a change table: per column its AP, interval, floor and verdict."""

    fusion: str
    label: str
    #: A variant or baseline: shown after the six methods, past a rule.
    extra: bool
    ap: tuple[float, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    floor: tuple[float, ...]
    verdict: tuple[str, ...]
    #: Per column, the query images holding a positive (method §9's evidence before a verdict).
    positive_images: tuple[float, ...]

    def cells(self) -> list[str]:
        """The row's AP cells as the markdown and the console show them."""
        return [
            ap_cell(*v)
            for v in zip(
                self.ap, self.low, self.high, self.verdict, self.positive_images, strict=True
            )
        ]


@dataclass(frozen=True)
class ChangeTable:
    """A change table of one run (and one localizer), ready for any format to render."""

    spec: ChangeSpec
    columns: tuple[Any, ...]
    rows: tuple[ChangeRow, ...]
    #: method §9's rows under the table, each (label, a cell per column).
    chance: tuple[tuple[str, list[str]], ...]
    #: The method whose sample counts the footer gives, and those counts in words.
    ref: str
    counts: str
    #: Lines every format shows under the table (Table P: the share of the gap closed).
    notes: tuple[str, ...]
    warnings: tuple[str, ...]
    localizer: str = ""

    def frame(self, value: str = "ap") -> pd.DataFrame:
        """One field of the rows (``ap``, ``low``, ``high``, ``floor``, ``verdict``) by column."""
        return pd.DataFrame(
            [getattr(r, value) for r in self.rows],
            index=pd.Index([r.fusion for r in self.rows], name="fusion"),
            columns=pd.Index(list(self.columns), name=self.spec.column),
        )


def change_table(
    summ: pd.DataFrame,
    table: str,
    methods: tuple[str, ...],
    warnings: Sequence[str] = (),
    localizer: str = "",
) -> ChangeTable:
    """Table ``table`` (``I``, ``S`` or ``P``) of a run's summary, for every format."""
    spec = CHANGE_TABLES[table]
    piv = {
        v: pivot(summ, table, methods, v)
        for v in ("ap", "ci_low", "ci_high", "floor", "verdict", "positive_images")
    }
    cols = list(piv["ap"].columns)
    rows = tuple(
        ChangeRow(
            str(m),
            METHOD_LABELS[str(m)],
            m not in FUSION_METHODS,
            *(tuple(piv[v].loc[m, c] for c in cols) for v in piv),
        )
        for m in piv["ap"].index
    )
    ref = box_sets(tuple(piv["ap"].index))[0][1]
    main = _pooled(summ, table)
    counts = "; ".join(
        f"{column_label(getattr(r, spec.column))}: {r.positives} positives / "
        f"{r.negatives} negatives" + (" (pixels)" if r.split in spec.pixel_columns else "")
        for r in main[main["fusion"] == ref].itertuples()
    )
    few = sum(v == "few" for r in rows for v in r.verdict)
    if few:
        needed = _needed(summ)
        warnings = (*warnings, few_warning(few, needed))
    return ChangeTable(
        spec,
        tuple(cols),
        rows,
        tuple(chance_rows(summ, table, methods)),
        ref,
        counts,
        (gap_line(summ, methods),) if spec.ceiling else (),
        tuple(warnings),
        localizer,
    )


def _needed(summ: pd.DataFrame) -> int:
    """``[report] min_positive_images`` of the run that wrote ``summ`` (its default if unknown)."""
    col = summ.get("positive_images_needed")
    return int(col.max()) if col is not None and len(col) else MIN_POSITIVE_IMAGES


def box_sets(methods: tuple[str, ...] | list[str]) -> list[tuple[str, str]]:
    """(label, reference method) of each sample set a change table's rows are scored on."""
    fused = next((m for m in methods if not is_unfused(m)), None)
    out = [("fused set", fused)] if fused else []
    nf = unfused(methods)
    if nf is not None:
        out.append(("original boxes", nf))
    return out


def chance_rows(
    summ: pd.DataFrame, table: str, methods: tuple[str, ...]
) -> list[tuple[str, list[str]]]:
    """The rows under a change table (method §9), each as (label, cells).

    Per sample set its floor, chance band and (Table P) ceiling, then the positive rate.
    """
    cols = list(pivot(summ, table, methods).columns)
    piv = {
        v: pivot(summ, table, methods, v)
        for v in ("floor", "chance_low", "chance_high", "ceiling", "positive_rate")
    }
    out = []
    sets = box_sets([m for m in methods if m in piv["floor"].index])
    for label, ref in sets:
        f, lo, hi = (piv[v].loc[ref] for v in ("floor", "chance_low", "chance_high"))
        out.append((f"floor, {label} (mean AP of random orders)", [number(f[c]) for c in cols]))
        out.append(
            (
                f"chance band, {label} (5th-95th percentile)",
                ["NaN" if lo[c] != lo[c] else f"{lo[c]:.2f}-{hi[c]:.2f}" for c in cols],
            )
        )
        if CHANGE_TABLES[table].ceiling:
            cl = piv["ceiling"].loc[ref]
            out.append(
                (f"ceiling, {label} (boxes scored by their RoC)", [number(cl[c]) for c in cols])
            )
    pr = piv["positive_rate"].loc[sets[0][1]] if sets else None
    if pr is not None:
        out.append(("positive rate (not the floor)", [number(pr[c], 3) for c in cols]))
    return out


def gap_line(summ: pd.DataFrame, methods: tuple[str, ...]) -> str:
    """Table P's share of the reachable gap, ``(AP - floor) / (ceiling - floor)``, per method."""
    g = pivot(summ, "P", methods, "gap_closed")
    parts = [
        f"{METHOD_LABELS[str(m)]} "
        + " / ".join(
            "NaN" if g.loc[m, c] != g.loc[m, c] else f"{100 * g.loc[m, c]:.0f}%" for c in g.columns
        )
        for m in g.index
    ]
    return (
        "Share of the reachable gap closed, (AP - floor) / (ceiling - floor), pixel / image: "
        + "; ".join(parts)
        + "."
    )

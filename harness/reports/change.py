"""Tables I, S and P from a run's summary (SPEC sections 8-10): their pivots, cells and chance rows.

Every format reads these: the markdown, CSV and LaTeX (:mod:`harness.reports.render`), the console
(:mod:`harness.cli.console`) and the page (:mod:`harness.reports.html.cells`).
"""

from __future__ import annotations

from typing import Any

import pandas as pd

from harness.evaluate.chance import VERDICT_MARKS
from harness.methods import METHOD_LABELS


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


def number(v: float, digits: int = 2) -> str:
    """``v`` to ``digits`` decimals; NaN as ``NaN``."""
    return "NaN" if v != v else f"{v:.{digits}f}"


def column_label(c: Any) -> str:
    """A table column's heading: a RoC-max to two decimals, a split by its name."""
    return f"{c:.2f}" if isinstance(c, float) else str(c)


def _cell(v: float, lo: float, hi: float, verdict: str = "") -> str:
    if v != v:
        return "NaN"
    mark = VERDICT_MARKS.get(verdict, "")
    return (f"{v:.2f} [{lo:.2f}, {hi:.2f}]" if lo == lo else f"{v:.2f}") + (
        f" {mark}" if mark else ""
    )


def change_cells(summ: pd.DataFrame, table: str, methods: tuple[str, ...]) -> pd.DataFrame:
    """Every AP cell of a change table as text: ``AP [interval] mark`` (the verdict's mark)."""
    ap, lo, hi, ver = (
        pivot(summ, table, methods, v) for v in ("ap", "ci_low", "ci_high", "verdict")
    )
    return pd.DataFrame(
        {
            c: [_cell(ap.loc[m, c], lo.loc[m, c], hi.loc[m, c], ver.loc[m, c]) for m in ap.index]
            for c in ap.columns
        },
        index=ap.index,
    )


def box_sets(methods: tuple[str, ...] | list[str]) -> list[tuple[str, str]]:
    """(label, reference method) of each sample set a change table's rows are scored on."""
    fused = next((m for m in methods if m != "rank_no_fusion"), None)
    out = [("fused set", fused)] if fused else []
    if "rank_no_fusion" in methods:
        out.append(("original boxes", "rank_no_fusion"))
    return out


def chance_rows(
    summ: pd.DataFrame, table: str, methods: tuple[str, ...]
) -> list[tuple[str, list[str]]]:
    """The rows under a change table (SPEC 9), each as (label, cells).

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
        if table == "P":
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
            "weighted by the strata's positives. The floor is the mean of the same figure over "
            "random orders within the same strata (SPEC 9)."
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

"""The console view of a run's tables (the same pivots as the markdown, method §10)."""

from __future__ import annotations


def print_change_table(console, t, run: str) -> None:
    """One change table (a :class:`~harness.reports.change.ChangeTable`) on the console.

    The markdown's cells with intervals and verdict marks, then floor, band and ceiling, the
    legend, the notes and the warnings.
    """
    from rich.markup import escape
    from rich.table import Table

    from harness.evaluate.chance import MARK_LEGEND
    from harness.reports.change import column_label

    out = Table(title=f"{t.spec.caption} ({run})")
    out.add_column("AP [95% CI]")
    for c in t.columns:
        out.add_column(column_label(c), justify="right")
    shown_sep = False
    for r in t.rows:
        if r.extra and not shown_sep:
            out.add_section()
            shown_sep = True
        out.add_row(escape(r.label), *(escape(c) for c in r.cells()))
    out.add_section()
    for label, vals in t.chance:
        out.add_row(label, *vals)
    console.print(out)
    console.print(MARK_LEGEND, markup=False)
    for n in t.notes:
        console.print(n, markup=False)
    for w in t.warnings:
        console.print(f"[bold yellow]{escape(w)}[/]")


def print_table_l(console, t) -> None:
    """Table L (method §11): a row per localizer and the fused row, then the floor.

    Then its cost table; every undefined cell is ``-`` with its reason as a footnote.
    """
    from rich.markup import escape
    from rich.table import Table

    from harness.evaluate.chance import MARK_LEGEND
    from harness.reports.leaderboard import COST_NOTE, WHY, leader_table
    from harness.runtime.costs import COST_COLUMNS

    v = leader_table(t)
    lt = Table(title=f"Table L: localizers (Table S at RoC-max {v.roc_max:.2f})")
    heads = ("localizer", *v.heads[:-1], f"S rank fusion - {v.first}")
    for c in heads:
        lt.add_column(c, justify="left" if c == "localizer" else "right")
    for name, cs in v.rows:
        lt.add_row(escape(name), *(escape(c.text()) for c in cs))
    lt.add_section()
    lt.add_row(
        f"floor ({v.first})", *([""] * len(v.recall_heads)), *(f"{f:.2f}" for f in v.floors), ""
    )
    console.print(lt)
    console.print(MARK_LEGEND, markup=False)
    if v.bounds_note:
        console.print(f"WARNING: {v.bounds_note}", markup=False)
    ct = Table(title="Table L: what each localizer costs")
    ct.add_column("localizer")
    for _, h, _ in COST_COLUMNS:
        ct.add_column(h, justify="right")
    for name, cs in v.cost_rows:
        ct.add_row(name, *(c.text() for c in cs))
    console.print(ct)
    console.print(COST_NOTE, markup=False)
    for m in sorted({*v.marks, *v.cost_marks}):
        console.print(f"{m}) -: {WHY[m]}.", markup=False)


def print_localization(console, rep, rec, also: bool = False) -> None:
    """One localizer's localization quality (all season pairs); ``also``: at the second radius."""
    from rich.table import Table

    from harness.reports.render import loc_columns

    loc = rep.localization_also if also else rep.localization
    radius = (
        rec["config"]["report"]["gt_radius_also"]
        if also
        else rec["config"]["retrieval"]["gt_radius_m"]
    )
    cols = loc_columns(loc)
    lt = Table(
        title=f"Localization quality of {rep.localizer} (ground truth: place within {radius:g} m)"
    )
    lt.add_column("props")
    lt.add_column("pair")
    for _, lab, _ in cols:
        lt.add_column(lab, justify="right")
    for r in loc[loc["season_pair"] == "all"].itertuples(index=False):
        lt.add_row(
            r.proposal_method,
            r.season_pair,
            *(
                str(int(getattr(r, c)))
                if d == 0
                else ("NaN" if getattr(r, c) != getattr(r, c) else f"{getattr(r, c):.{d}f}")
                for c, _, d in cols
            ),
        )
    console.print(lt)
    print(f"  per season pair: localization{'_also' if also else ''}.md")


def print_block(console, rep, rec) -> None:
    """One block's Tables I, S and P and its paired comparisons (Table S, last RoC-max)."""
    name = f"{rec['config']['name']}, localizer {rep.localizer}"
    from harness.reports.change import CHANGE_TABLES, change_table

    for table in CHANGE_TABLES:
        t = change_table(rep.summary, table, rep.methods, rep.warnings[table])
        print_change_table(console, t, name)
    summ = rep.summary
    cmp_ = summ[
        (summ["table"] == "S")
        & (summ["proposal_method"] == "all")
        & (summ["season_pair"] == "all")
        & summ["diff"].notna()
    ]
    if len(cmp_):
        from harness.reports.render import HOLM_MARK, holm_sentence

        last = cmp_[cmp_["roc_max"] == cmp_["roc_max"].max()]
        print(
            "Paired comparisons with rank fusion (Table S, RoC-max "
            f"{last['roc_max'].iloc[0]:.2f}; all tables: comparisons.md):"
        )
        print("  " + holm_sentence(cmp_, "Table S"))
        for r in last.itertuples():
            print(
                f"  {r.fusion} - rank_fusion = {r.diff:+.2f} [{r.diff_ci_low:+.2f}, "
                f"{r.diff_ci_high:+.2f}]"
                + (
                    f", sign flips in {100 * r.sign_flip_share:.0f}% of resamples"
                    if r.sign_flip_share == r.sign_flip_share
                    else ""
                )
                + (f" {HOLM_MARK}" if getattr(r, "holm_survives", False) else "")
            )

"""How the tables read (method §10): markdown, CSV and LaTeX renderers of one table spec.

The localization table, Tables I, S and P (their pivots and cells from
:mod:`harness.reports.change`), the paired comparisons; the console (:mod:`harness.cli`) and the
page (:mod:`harness.reports.html.page`) read the same pivots and intros.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import pandas as pd

from harness.evaluate.chance import MARK_LEGEND, VERDICT_TEX, few_text
from harness.evaluate.localization import CLEAN_ROC
from harness.methods import FUSION_METHODS, METHOD_LABELS
from harness.reports.change import CHANGE_TABLES, ChangeTable, column_label, number
from harness.reports.texfmt import tex_escape as _tex_escape


def recall_ns(loc: pd.DataFrame) -> list[int]:
    """The N of every ``recall_at_N`` column of a localization table (``[report] recall_at``)."""
    return sorted(int(c[10:]) for c in loc.columns if re.fullmatch(r"recall_at_\d+", c))


def loc_columns(loc: pd.DataFrame) -> list[tuple[str, str, int]]:
    """(column, heading, decimals) of a localization table: R@N for each ``[report] recall_at``."""
    ns = recall_ns(loc)
    return [
        ("subimages", "n", 0),
        *((f"recall_at_{n}", f"R@{n}", 2) for n in ns),
        ("median_r", "med r", 3),
        ("chance_recall_at_1", "chance R@1", 3),
        *((f"clean_recall_at_{n}", f"clean R@{n}", 2) for n in ns),
        ("clean_median_r", "clean med r", 3),
    ]


def heading_suffix(localizer: str) -> str:
    """What every table heading adds: the localizer it measured (method §11)."""
    return f" (localizer: {localizer})" if localizer else ""


def localization_markdown(loc: pd.DataFrame, gt_radius_m: float, localizer: str = "") -> str:
    """The localization table as markdown (recall@N, median r, chance rates)."""
    cols = loc_columns(loc)
    head = (
        "| proposals | season pair | "
        + " | ".join(lab for _, lab, _ in cols)
        + " |\n|---|---|"
        + "---:|" * len(cols)
        + "\n"
    )
    body = "".join(
        f"| {r.proposal_method} | {r.season_pair} | "
        + " | ".join(
            str(int(getattr(r, c))) if d == 0 else number(float(getattr(r, c)), d)
            for c, _, d in cols
        )
        + " |\n"
        for r in loc.itertuples(index=False)
    )
    foot = (
        "\nLocalization quality of the engines whose ranks every change figure rests on. "
        "Ground truth: the place of "
        f"the reference frame (frames within {gt_radius_m:g} m, method §6). R@k: share "
        "of query subimages whose "
        "place ranks within the first k; median r: median normalised rank (0.5 = chance); "
        "clean: subimages of "
        f"annotated frames with RoC <= {CLEAN_ROC}. R@1 by chance: mean 1/L.\n"
    )
    return f"# Localization quality{heading_suffix(localizer)}\n\n" + head + body + foot


# ------------------------------------------------------------------ rendering


def table_csv(table: pd.DataFrame, localizer: str | None = None, header: bool = True) -> str:
    """One row per method id (first column ``fusion``), one column per split, two decimals.

    With ``localizer`` a first column names it (a run of several localizers: one CSV, a block of
    rows each; ``header`` only on the first).
    """
    pre = "" if localizer is None else "localizer,"
    lines = [pre + "fusion," + ",".join(column_label(c) for c in table.columns)] if header else []
    cell = "" if localizer is None else (f'"{localizer}",' if "," in localizer else f"{localizer},")
    for m, row in table.iterrows():
        lines.append(
            cell
            + str(m)
            + ","
            + ",".join("nan" if np.isnan(v) else f"{v:.2f}" for v in row.to_numpy())
        )
    return "\n".join(lines) + "\n"


def table_markdown(t: ChangeTable) -> str:
    """A change table as markdown: the six methods, then the variants and baselines.

    Cells AP [95% interval] and the verdict's mark; then method §9's chance rows, the legend, the
    counts, the notes and the warnings.
    """
    spec, cols = t.spec, t.columns
    head = (
        "| AP [95% CI] | "
        + " | ".join(column_label(c) for c in cols)
        + " |\n|---|"
        + "---:|" * len(cols)
        + "\n"
    )
    lines, first_extra = [], True
    for r in t.rows:
        if r.extra and first_extra:
            lines.append("| *variants and baselines* |" + " |" * len(cols) + "\n")
            first_extra = False
        lines.append(f"| {r.label} | " + " | ".join(r.cells()) + " |\n")
    for label, vals in t.chance:
        lines.append(f"| *{label}* | " + " | ".join(vals) + " |\n")
    return (
        f"# {spec.title}{heading_suffix(t.localizer)}\n\n{spec.intro}\n\n"
        + head
        + "".join(lines)
        + f"\n{MARK_LEGEND} Floor: the mean AP of random orders of the same samples"
        + spec.floor_within
        + f". Counts ({t.ref}): {t.counts}. Intervals: 95% bootstrap over query images; "
        "the paired differences with rank fusion are in comparisons.md.\n"
        + "".join(f"\n{n}\n" for n in t.notes)
        + "".join(f"\n**{w}**\n" for w in t.warnings)
    )


def change_latex(t: ChangeTable) -> str:
    """A change table as a booktabs ``tabular``: APs with verdict marks, then the chance rows."""
    return table_latex(
        t.frame(),
        t.spec.corner,
        t.localizer,
        t.frame("verdict"),
        list(t.chance),
        t.frame("positive_images"),
    )


def table_latex(
    t: pd.DataFrame,
    caption_cols: str = "",
    localizer: str = "",
    verdicts: pd.DataFrame | None = None,
    extra: list[tuple[str, list[str]]] | None = None,
    positive_images: pd.DataFrame | None = None,
) -> str:
    """A booktabs ``tabular`` of one table.

    Two decimals; the variants and baselines come after a rule. The localizer is named in a
    comment line above it. ``verdicts`` (the same shape) add method §9's marks, and a ``few`` cell
    says "too few positives (n)" with ``positive_images``' n; ``extra`` rows (floor, chance band,
    ceiling) come after a last rule.
    """
    cols = list(t.columns)
    out = [f"% localizer: {localizer}"] if localizer else []
    out += [
        r"\begin{tabular}{l" + "r" * len(cols) + "}",
        r"\toprule",
        " & ".join(
            [_tex_escape(caption_cols or "Method")] + [_tex_escape(column_label(c)) for c in cols]
        )
        + r" \\",
        r"\midrule",
    ]
    first_extra = True
    for m, row in t.iterrows():
        if m not in FUSION_METHODS and first_extra and m in METHOD_LABELS:
            out.append(r"\midrule")
            first_extra = False
        label = METHOD_LABELS.get(str(m), str(m))
        marks = (
            [_tex_mark(verdicts, positive_images, m, c) for c in cols]
            if verdicts is not None
            else [""] * len(cols)
        )
        out.append(
            " & ".join(
                [_tex_escape(label)]
                + [
                    "--" if v != v else f"{v:.2f}{mk}"
                    for v, mk in zip(row.to_numpy(), marks, strict=True)
                ]
            )
            + r" \\"
        )
    if extra:
        out.append(r"\midrule")
        out += [
            " & ".join([r"\emph{" + _tex_escape(lab) + "}"] + [_tex_escape(v) for v in vals])
            + r" \\"
            for lab, vals in extra
        ]
    out += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(out) + "\n"


def _tex_mark(verdicts: pd.DataFrame, positives: pd.DataFrame | None, m: Any, c: Any) -> str:
    """A LaTeX cell's verdict mark, or ``few``'s words in small type."""
    v = str(verdicts.loc[m, c])
    if v == "few":
        n = positives.loc[m, c] if positives is not None else float("nan")
        return r" {\scriptsize " + _tex_escape(few_text(int(n) if n == n else 0)) + "}"
    return VERDICT_TEX.get(v, "")


#: How the comparisons mark a difference that survives Holm's correction over its table.
HOLM_MARK = "[Holm]"


def holm_sentence(main: pd.DataFrame, table_title: str) -> str:
    """How many of a table's paired differences were tested and how many survive Holm."""
    tested = int(main["holm_tested"].max()) if "holm_tested" in main and len(main) else 0
    kept = int(main["holm_survives"].sum()) if "holm_survives" in main else 0
    if not tested:
        return f"{table_title}: no paired difference to test."
    return (
        f"{table_title}: {kept} of the {tested} differences from rank fusion tested in this "
        f"table survive a Holm correction over those {tested} (family-wise error 5%); they are "
        f"marked {HOLM_MARK}. The others' intervals may clear 0 by chance among so many."
    )


def comparisons_markdown(summ: pd.DataFrame, methods: tuple[str, ...], localizer: str = "") -> str:
    """Every method against rank fusion, in words, for every pooled column of Tables I, S and P.

    Each table's differences are one family for Holm's correction
    (:func:`harness.evaluate.metrics.holm`): the survivors are marked, and the table's heading says
    how many were tested.
    """
    lines = [
        f"# Paired comparisons with rank fusion{heading_suffix(localizer)}",
        "",
        (
            "Each line: AP(method) - AP(rank fusion) [95% interval of the difference over the "
            "same bootstrap resamples of query "
            "images]; 'sign flips' is the share of resamples in which the difference has the "
            "other sign; p: two-sided, from the bootstrap standard error of the difference (normal "
            "approximation; where the resampled differences are skewed it can exceed 0.05 while "
            "the percentile interval excludes 0). "
            f"{HOLM_MARK}: the difference survives Holm's correction over every difference of "
            "its table (Tables I, S and P are three families)."
        ),
        "",
    ]
    for table, spec in CHANGE_TABLES.items():
        main = summ[
            (summ["table"] == table)
            & (summ["proposal_method"] == "all")
            & (summ["season_pair"] == "all")
        ]
        if not len(main):
            continue
        lines += [holm_sentence(main, spec.title), ""]
        for split, g in main.groupby("split", sort=False):
            lines.append(f"## {spec.title}, {split}")
            lines.append("")
            for r in g.itertuples():
                if r.fusion == "rank_fusion" or r.diff != r.diff:
                    continue
                flips = (
                    f"sign flips in {100 * r.sign_flip_share:.0f}% of resamples"
                    if r.sign_flip_share == r.sign_flip_share
                    else "no difference"
                )
                p = getattr(r, "p_value", float("nan"))
                ptxt = "" if p != p else ", p < 0.001" if p < 0.001 else f", p = {p:.3f}"
                mark = f" {HOLM_MARK}" if getattr(r, "holm_survives", False) else ""
                lines.append(
                    f"- {METHOD_LABELS[r.fusion]} - rank fusion = {r.diff:+.2f} "
                    f"[{r.diff_ci_low:+.2f}, {r.diff_ci_high:+.2f}] ({flips}{ptxt}){mark}"
                )
            lines.append("")
    return "\n".join(lines)


def localization_latex(loc: pd.DataFrame, localizer: str = "") -> str:
    """The localization table (all season pairs) as a booktabs ``tabular``."""
    ns = recall_ns(loc)
    t = loc[loc["season_pair"] == "all"].set_index("proposal_method")[
        [*(f"recall_at_{n}" for n in ns), "median_r", "chance_recall_at_1", "clean_recall_at_1"]
    ]
    t.columns = [*(f"R@{n}" for n in ns), "median r", "R@1 by chance", "clean R@1"]
    return table_latex(t, "Proposals", localizer)

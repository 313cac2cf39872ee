"""Report tables beyond the method's: one spec, rendered to CSV, markdown, LaTeX, console, page.

A table is a :class:`TableSpec`: an id (its files are ``table<id>.csv|md|tex``), a title, an
intro, its columns and a ``compute`` function of the run's config and report blocks (one
:class:`~harness.reports.blocks.Reports` per localizer, method §11) returning one row per line
of the table, or None where the run has nothing for it. :func:`register_table` adds it;
``write_reports`` then writes its three files, ``harness reproduce`` prints it after the other
tables and the report page shows it (its AP cells coloured against their floors like every other
change figure). The page and the console read the CSV back, so ``harness report OUT`` rebuilds
the page of an earlier run from its files.

Column kinds: ``text``, ``int``, ``num`` (``digits`` decimals), ``ap`` (the frame holds
``<key>_ap``, ``<key>_ci_low``, ``<key>_ci_high`` and ``<key>_floor``: shown as AP [interval]
with its floor) and ``diff`` (``<key>_diff``, ``<key>_diff_ci_low``, ``<key>_diff_ci_high``: a
paired difference with its interval).
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from harness.methods import Registry
from harness.reports.texfmt import tex_escape

KINDS = ("text", "int", "num", "ap", "diff")
#: Ids of the method's own tables (and ``detect``'s Table D): a registered table takes another.
RESERVED_IDS = frozenset({"1", "I", "S", "P", "L", "D"})
SUFFIXES = {
    "ap": ("ap", "ci_low", "ci_high", "floor"),
    "diff": ("diff", "diff_ci_low", "diff_ci_high"),
}


@dataclass(frozen=True)
class Column:
    """One column of a table: the frame column(s) it reads, its header and how it is shown."""

    key: str
    header: str
    kind: str = "num"
    digits: int = 2

    def fields(self) -> list[str]:
        """The frame's columns this column reads."""
        return (
            [f"{self.key}_{s}" for s in SUFFIXES[self.kind]]
            if self.kind in SUFFIXES
            else [self.key]
        )


@dataclass(frozen=True)
class TableSpec:
    """A report table: ``compute(cfg, blocks)`` -> a row per line or None, shown as ``columns``."""

    id: str
    title: str
    intro: str
    columns: tuple[Column, ...]
    compute: Callable[[Any, Sequence[Any]], pd.DataFrame | None]

    @property
    def stem(self) -> str:
        """The files' name without suffix: ``table<id>``."""
        return f"table{self.id}"


#: Registered tables, in the order they are written and shown.
TABLES: Registry[TableSpec] = Registry("table")
#: Modules of the harness that register a table when imported (:func:`load_builtin` imports
#: them): a table shipped with the harness is a module and a line here.
BUILTIN_MODULES: tuple[str, ...] = ()


def load_builtin() -> dict[str, TableSpec]:
    """Import :data:`BUILTIN_MODULES` (each registers its table once) and return the registry."""
    for name in BUILTIN_MODULES:
        importlib.import_module(name)
    return TABLES


def register_table(spec: TableSpec) -> None:
    """Add ``spec`` to the reports of every later run in this process.

    Raises:
        ValueError: the id is the method's, taken, or not alphanumeric; a column's kind unknown.
    """
    if not re.fullmatch(r"[A-Za-z0-9]+", spec.id) or spec.id in RESERVED_IDS:
        raise ValueError(f"table id {spec.id!r}: letters and digits, not one of {RESERVED_IDS}")
    bad = [c.key for c in spec.columns if c.kind not in KINDS]
    if bad:
        raise ValueError(f"table {spec.id!r}: column(s) {bad} of unknown kind; kinds: {KINDS}")
    TABLES.add(spec.id, spec)


def _num(v: Any, digits: int, sign: bool = False) -> str:
    v = float(v)
    return "" if v != v else f"{v:+.{digits}f}" if sign else f"{v:.{digits}f}"


def cell(col: Column, row: Any) -> str:
    """The text of ``col``'s cell in ``row``: what markdown, LaTeX and the console show."""
    if col.kind == "text":
        return str(row[col.key])
    if col.kind == "int":
        return str(int(row[col.key]))
    if col.kind == "num":
        return _num(row[col.key], col.digits)
    k = col.key
    if col.kind == "ap":
        ap = _num(row[f"{k}_ap"], col.digits)
        lo, hi = _num(row[f"{k}_ci_low"], col.digits), _num(row[f"{k}_ci_high"], col.digits)
        fl = _num(row[f"{k}_floor"], col.digits)
        return ap + (f" [{lo}, {hi}]" if lo else "") + (f" (floor {fl})" if fl else "")
    d = _num(row[f"{k}_diff"], col.digits, True)
    lo, hi = (_num(row[f"{k}_diff_{s}"], col.digits, True) for s in ("ci_low", "ci_high"))
    return d + (f" [{lo}, {hi}]" if d and lo else "")


def check_frame(spec: TableSpec, frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` cut to the columns the spec reads, in their order.

    Raises:
        ValueError: a column the spec reads is missing (naming the table and the column).
    """
    want = [f for c in spec.columns for f in c.fields()]
    miss = [f for f in want if f not in frame.columns]
    if miss:
        raise ValueError(f"table {spec.id!r}: compute returned no column(s) {miss}")
    return frame[want].reset_index(drop=True)


def to_csv(frame: pd.DataFrame) -> str:
    """The CSV file: every column the spec reads, full precision."""
    return str(frame.to_csv(index=False, lineterminator="\n"))


def to_markdown(spec: TableSpec, frame: pd.DataFrame) -> str:
    """The markdown file: heading, intro, one row per line."""
    out = [f"## Table {spec.id}: {spec.title}", "", spec.intro, ""]
    out.append("| " + " | ".join(c.header for c in spec.columns) + " |")
    out.append("|" + "|".join("---" if c.kind == "text" else "---:" for c in spec.columns) + "|")
    for _, r in frame.iterrows():
        out.append("| " + " | ".join(cell(c, r) for c in spec.columns) + " |")
    return "\n".join(out) + "\n"


def to_latex(spec: TableSpec, frame: pd.DataFrame) -> str:
    """The LaTeX file: a ``tabular`` with a caption comment, booktabs rules."""
    align = "".join("l" if c.kind == "text" else "r" for c in spec.columns)
    out = [f"% Table {spec.id}: {spec.title}", f"\\begin{{tabular}}{{{align}}}", "\\toprule"]
    out.append(" & ".join(tex_escape(c.header) for c in spec.columns) + " \\\\")
    out.append("\\midrule")
    for _, r in frame.iterrows():
        out.append(" & ".join(tex_escape(cell(c, r)) for c in spec.columns) + " \\\\")
    out += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(out) + "\n"


def to_console(spec: TableSpec, frame: pd.DataFrame) -> Any:
    """A ``rich`` table of the same cells as the markdown."""
    from rich.table import Table

    t = Table(title=f"Table {spec.id}: {spec.title}", caption=spec.intro, caption_justify="left")
    for c in spec.columns:
        t.add_column(c.header, justify="left" if c.kind == "text" else "right")
    for _, r in frame.iterrows():
        t.add_row(*(cell(c, r) for c in spec.columns))
    return t


def written(out: Path) -> list[tuple[TableSpec, pd.DataFrame]]:
    """The registered tables this run directory holds, each with its frame (read from its CSV)."""
    return [
        (spec, pd.read_csv(out / f"{spec.stem}.csv", keep_default_na=False, na_values=[""]))
        for spec in load_builtin().values()
        if (out / f"{spec.stem}.csv").is_file()
    ]

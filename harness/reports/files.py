"""The files one run's reports write, and the removal of an earlier run's that this one did not."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from harness.reports import tables as report_tables
from harness.runtime.cache import write_text

log = logging.getLogger(__name__)


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


#: The files a table is written to (``<stem>.csv`` and so on).
TABLE_SUFFIXES = ("csv", "md", "tex")


def _remove_unwritten(paths: Sequence[Path], keep: set[Path]) -> int:
    """Remove those of ``paths`` (the harness's own file names) that this run did not write.

    Only these exact names: a file of the user's beside them (``tableL.notes``) is left alone.
    """
    gone = [p for p in paths if p.is_file() and p.resolve() not in keep]
    for p in gone:
        p.unlink()
    return len(gone)


@dataclass
class ReportFiles:
    """The files one call of :func:`write_reports` writes (the rest of ``out`` is stale)."""

    out: Path
    multi: bool
    written: set[Path] = field(default_factory=set)

    def put(self, path: Path) -> Path:
        """``path`` (under ``out``), recorded as written by this run."""
        self.written.add(path.resolve())
        return path

    def text(self, name: str, text: str) -> None:
        """Write ``out/name`` atomically and record it."""
        write_text(self.put(self.out / name), text)

    def tag(self, df: pd.DataFrame, name: str) -> pd.DataFrame:
        """``df`` with a first ``localizer`` column where the run has several localizers."""
        if self.multi and "localizer" not in df.columns:
            df = df.copy()
            df.insert(0, "localizer", name)
        return df


def remove_old_reports(files: ReportFiles) -> None:
    """Remove the reports of an earlier run into ``out`` that this run did not write."""
    out, written = files.out, files.written
    stale = _remove_stale(out / "splits", "*.parquet", written) + _remove_stale(
        out / "plots", "pr_*.png", written
    )
    stale += _remove_stale(out / "locmaps", "*", written)
    stems = ["tableL", "localization_also", *(spec.stem for spec in report_tables.TABLES.values())]
    stale += _remove_unwritten([out / f"{t}.{x}" for t in stems for x in TABLE_SUFFIXES], written)
    if stale:
        log.info(
            "reports: removed %d file(s) of an earlier run that this run no longer writes", stale
        )

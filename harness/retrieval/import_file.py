"""An imported ranked-list file (method §12): its schema, ``--import NAME=FILE``, reading.

The scoring of its rows against a run is :mod:`harness.retrieval.imported`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.errors import RetrievalError
from harness.methods import LOCALIZER_NAME_RULE, is_localizer_name
from harness.records import SUBIMAGE_KEY

KEY = SUBIMAGE_KEY

log = logging.getLogger(__name__)


BOX = ["x1", "y1", "x2", "y2"]


REQUIRED = [*KEY[:3], "proposal_method", "box_id", *BOX, "r_session", "ranked", "L"]


OPTIONAL = ["scores"]


#: Columns read under their older names (before the one vocabulary), each with a warning.
RENAMED = {"method": "proposal_method"}


SCORE_KINDS = ("distance", "similarity")


@dataclass(frozen=True)
class ImportSpec:
    """One ``--import NAME=FILE``: the localizer's name and its rank file."""

    name: str
    path: Path


def parse_import_arg(text: str) -> ImportSpec:
    """``NAME=FILE`` or a bare ``FILE`` (the name is then the file's stem).

    Raises:
        RetrievalError: An empty name or file, or a name that is not a plain word.
    """
    name, sep, file = text.partition("=")
    if not sep or "/" in name or not name:
        name, file = Path(text).stem, text
    if not file:
        raise RetrievalError(f"--import {text!r}: give NAME=FILE or FILE")
    check_localizer_name(name, f"--import {text!r}")
    return ImportSpec(name, Path(file))


def check_localizer_name(name: str, where: str) -> str:
    """A localizer name: shown in tables and used in file names, so a plain word.

    The same rule as ``[[localizers]] name`` (:func:`harness.methods.is_localizer_name`).

    Raises:
        RetrievalError: It is not 1-64 ASCII letters, digits, ``.``, ``_``, ``-`` or ``+``
            starting with a letter or digit.
    """
    if not is_localizer_name(name):
        raise RetrievalError(f"{where}: localizer name {name!r}: expected {LOCALIZER_NAME_RULE}")
    return name


class Rows:
    """Row numbering for messages: CSV line numbers (header = line 1) or parquet rows (1-based)."""

    def __init__(self, path: Path, csv: bool) -> None:
        self.path, self.csv = path, csv

    def name(self, i: int) -> str:
        """How an error names row ``i``: a CSV line or a parquet row."""
        return f"line {i + 2}" if self.csv else f"row {i + 1}"

    def fail(self, bad: np.ndarray | Sequence[int], what: str, example: str = "") -> None:
        """Raise one error for the rows ``bad`` (indices) when there are any."""
        idx = np.flatnonzero(bad) if isinstance(bad, np.ndarray) and bad.dtype == bool else bad
        idx = list(idx)
        if not idx:
            return
        n = len(idx)
        ex = f" (e.g. {self.name(int(idx[0]))}{': ' + example if example else ''})"
        raise RetrievalError(f"{self.path}: {n} row{'s' if n != 1 else ''} {what}{ex}")


def _int_list(v: Any) -> list[int] | None:
    """A parquet list or a CSV string of integers; None when it is anything else."""
    if isinstance(v, str):
        parts = v.split()
        try:
            return [int(p) for p in parts]
        except ValueError:
            return None
    if isinstance(v, (list, tuple, np.ndarray)):
        out = []
        for x in v:
            if isinstance(x, (bool, np.bool_)) or x is None:
                return None
            whole = isinstance(x, (float, np.floating)) and math.isfinite(x) and x.is_integer()
            if not (isinstance(x, (int, np.integer)) or whole):
                return None
            out.append(int(x))
        return out
    return None


def _float_list(v: Any) -> list[float] | None:
    """A parquet list or a CSV string of numbers; None when it is anything else."""
    items = v.split() if isinstance(v, str) else v
    if not isinstance(items, (list, tuple, np.ndarray)):
        return None
    out = []
    for x in items:
        if x is None or isinstance(x, (bool, np.bool_)):
            return None
        try:
            out.append(float(x))
        except (TypeError, ValueError):
            return None
    return out


def _read_table(path: Path) -> tuple[pd.DataFrame, bool]:
    """The rank file's table (a CSV as strings) and whether it is a CSV."""
    if not path.exists():
        raise RetrievalError(f"{path}: rank file not found")
    if path.is_dir():
        raise RetrievalError(f"{path}: is a directory; give the rank file (.parquet or .csv)")
    csv = path.suffix.lower() != ".parquet"
    try:
        if csv:
            df = pd.read_csv(path, dtype=str, keep_default_na=False, encoding="utf-8")
        else:
            df = pd.read_parquet(path)
    except PermissionError:
        raise RetrievalError(f"{path}: not readable (permission denied)") from None
    except UnicodeDecodeError as err:
        raise RetrievalError(
            f"{path}: not a UTF-8 CSV ({err.reason} at byte {err.start})"
        ) from None
    except (OSError, ValueError) as err:
        kind = "CSV" if csv else "parquet"
        raise RetrievalError(f"{path}: not a readable {kind} file ({err})") from None
    return df, csv


def _read_lists(df: pd.DataFrame, out: pd.DataFrame, rows: Rows) -> None:
    """``ranked`` (and ``scores``) into ``out`` as Python lists, every value checked."""
    ranked = [_int_list(v) for v in df["ranked"]]
    bad_i = [i for i, v in enumerate(ranked) if v is None]
    rows.fail(
        bad_i,
        "have a 'ranked' that is not a list of integer frame utimes (CSV: space-separated)",
        f"{str(df['ranked'].iloc[bad_i[0]])[:40]!r}" if bad_i else "",
    )
    rows.fail([i for i, v in enumerate(ranked) if not v], "have an empty 'ranked' list")
    rows.fail(
        [i for i, v in enumerate(ranked) if v is not None and len(set(v)) != len(v)],
        "have a 'ranked' list that repeats a frame",
    )
    out["ranked"] = ranked
    long = out["L"].to_numpy() < np.array([len(v or []) for v in ranked])
    rows.fail(long, "have L shorter than their 'ranked' list")
    if "scores" in df.columns:
        scores = [_float_list(v) for v in df["scores"]]
        rows.fail(
            [i for i, v in enumerate(scores) if v is None],
            "have 'scores' that are not a list of numbers (CSV: space-separated)",
        )
        rows.fail(
            [
                i
                for i, (s, r) in enumerate(zip(scores, ranked, strict=True))
                if len(s or []) != len(r or [])
            ],
            "have 'scores' of another length than 'ranked'",
        )
        nonfinite = [i for i, s in enumerate(scores) if not all(math.isfinite(x) for x in s or [])]
        rows.fail(nonfinite, "have non-finite scores (NaN or inf)")
        out["scores"] = scores


def read_import(path: Path) -> tuple[pd.DataFrame, Rows]:
    """A rank file (CSV or parquet) as a typed table; every value checked.

    Returns:
        The table (``ranked`` and ``scores`` as Python lists) and its row numbering.

    Raises:
        RetrievalError: The file is missing, unreadable, lacks a column, or a value has the
            wrong type: one message naming the file, the count and one example row.
    """
    path = Path(path)
    df, csv = _read_table(path)
    rows = Rows(path, csv)
    if "distance" in df.columns and "scores" not in df.columns:
        raise RetrievalError(
            f"{path}: column 'distance' is not read (a distance to what?): give 'scores', "
            "parallel to 'ranked', one score per listed frame, and set [import] score_kind "
            "(method §12)"
        )
    for old, new in RENAMED.items():
        if old in df.columns and new in df.columns:
            raise RetrievalError(
                f"{path}: columns {old!r} and {new!r} both given; {old!r} is {new!r}'s old name: "
                "keep one"
            )
        if old in df.columns:
            log.warning("%s: column %r read as %r (its name now): rename it", path, old, new)
            df = df.rename(columns={old: new})
    miss = [c for c in REQUIRED if c not in df.columns]
    if miss:
        raise RetrievalError(
            f"{path}: missing column(s) {miss}; required: {REQUIRED}, optional: {OPTIONAL}"
        )
    df = df.reset_index(drop=True)
    out = pd.DataFrame(index=df.index)
    for c in ("q_session", "q_camera", "r_session", "proposal_method"):
        s = df[c]
        bad = s.isna().to_numpy() | (s.astype(str).str.strip() == "").to_numpy()
        rows.fail(bad, f"have no {c}")
        out[c] = s.astype(str).str.strip()
    for c in ("q_utime", "box_id", "L"):
        num = pd.to_numeric(df[c], errors="coerce")
        vals = num.to_numpy(np.float64)
        bad = ~np.isfinite(vals) | (vals != np.round(vals))
        i = int(np.flatnonzero(bad)[0]) if bad.any() else 0
        rows.fail(bad, f"have a {c} that is not an integer", f"{c} = {df[c].iloc[i]!r}")
        out[c] = vals.astype(np.int64)
    rows.fail(out["L"].to_numpy() < 1, "have L < 1")
    for c in BOX:
        vals = pd.to_numeric(df[c], errors="coerce").to_numpy(np.float64)
        bad = ~np.isfinite(vals)
        i = int(np.flatnonzero(bad)[0]) if bad.any() else 0
        rows.fail(bad, f"have a {c} that is not a finite number", f"{c} = {df[c].iloc[i]!r}")
        out[c] = vals
    flat = (out["x2"] <= out["x1"]) | (out["y2"] <= out["y1"])
    rows.fail(flat.to_numpy(), "have a box with x2 <= x1 or y2 <= y1 (reversed or empty)")
    _read_lists(df, out, rows)
    return out, rows

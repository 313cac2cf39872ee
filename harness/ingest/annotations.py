"""Annotation tables (method §2): loading, validation, importers and a labelling exporter.

The canonical table is a CSV with columns ``session, camera, utime, status, x1, y1, x2, y2, label``:
one row per change box, and one row with empty box fields for a ``no-change`` frame.

Labelling tools know images by file name. The exporter names each image
``<session>__<camera>__<utime>.png``; the importers map names of that form back to frame keys.
"""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.errors import AnnotationError
from harness.ingest.names import frames_by_image
from harness.inputs import check_input
from harness.records import FRAME_KEY

COLUMNS = ["session", "camera", "utime", "status", "x1", "y1", "x2", "y2", "label"]
STATUSES = ("change", "no-change")
_NAME = re.compile(r"^(?P<session>.+?)__(?P<camera>.+?)__(?P<utime>-?\d+)(\.[A-Za-z0-9]+)?$")


def image_name(session: str, camera: str, utime: int, ext: str = ".png") -> str:
    """The labelling file name of a frame: ``<session>__<camera>__<utime><ext>``."""
    return f"{session}__{camera}__{int(utime)}{ext}"


def parse_image_name(name: str, where: str) -> tuple[str, str, int]:
    """(session, camera, utime) of a labelling file name.

    Raises:
        AnnotationError: The name is not ``<session>__<camera>__<utime>.<ext>`` (``where``
            names the file).
    """
    m = _NAME.match(Path(name).name)
    if not m:
        raise AnnotationError(
            f"{where}: image name {name!r} is not of the form <session>__<camera>__<utime>.<ext>"
        )
    return m["session"], m["camera"], int(m["utime"])


def _utimes(values: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """(int64 utimes, bad) of a column: only whole numbers that fit in 64 bits are utimes.

    ``1333195231000000.7`` or a 25-digit number is bad, never truncated or overflowed.
    """
    out = np.zeros(len(values), np.int64)
    bad = np.zeros(len(values), bool)
    for i, v in enumerate(values.tolist()):
        text = str(v).strip()
        whole = isinstance(v, float | np.floating) and float(v).is_integer()
        if isinstance(v, int | np.integer) or whole:
            text = str(int(v))
        if re.fullmatch(r"-?\d{1,19}", text) and -(2**63) <= int(text) < 2**63:
            out[i] = int(text)
        else:
            bad[i] = True
    return out, bad


def validate_annotations(
    df: pd.DataFrame,
    frames: pd.DataFrame | None,
    where: str,
    lines: np.ndarray | None = None,
) -> pd.DataFrame:
    """Check an annotation table; return it normalised (types, sorted).

    ``lines`` are the CSV lines the rows start on (default: the row index + 2, a header and no
    blank line).

    Raises:
        AnnotationError: naming the row (CSV line) and what is wrong: missing columns, unknown
            status, a change box that is missing, of zero area or outside the image, an unknown
            frame, a frame both change and no-change, duplicate rows.
    """
    missing = [c for c in COLUMNS[:8] if c not in df.columns]
    if missing:
        raise AnnotationError(f"{where}: missing column(s) {missing}; expected {COLUMNS}")
    df = df.copy()
    if "label" not in df.columns:
        df["label"] = ""
    df["label"] = df["label"].fillna("").astype(str)
    line = df.index.to_numpy() + 2 if lines is None else np.asarray(lines)  # header: line 1

    def fail(mask: np.ndarray, what: str) -> None:
        if mask.any():
            i = int(np.nonzero(mask)[0][0])
            raise AnnotationError(
                f"{where}: line {line[i]}: {what} ({int(mask.sum())} row(s) in all)"
            )

    ut, bad = _utimes(df["utime"])
    if bad.any():
        first = df["utime"].iloc[int(np.nonzero(bad)[0][0])]
        fail(bad, f"utime {str(first)!r} is not a whole number of microseconds within 64 bits")
    df["utime"] = ut
    df["session"] = df["session"].astype(str)
    df["camera"] = df["camera"].astype(str)
    fail(~df["status"].isin(STATUSES).to_numpy(), f"status must be one of {STATUSES}")
    for c in ("x1", "y1", "x2", "y2"):
        df[c] = pd.to_numeric(df[c], errors="coerce")
    box = df[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    chg = (df["status"] == "change").to_numpy()
    fail(chg & ~np.isfinite(box).all(axis=1), "a change row needs a numeric box x1, y1, x2, y2")
    fail(~chg & np.isfinite(box).any(axis=1), "a no-change row must leave the box empty")
    with np.errstate(invalid="ignore"):
        fail(
            chg & ((box[:, 2] <= box[:, 0]) | (box[:, 3] <= box[:, 1])),
            "box has zero or negative area",
        )
        fail(chg & ((box[:, 0] < 0) | (box[:, 1] < 0)), "box starts outside the image")
    keys = FRAME_KEY
    if frames is not None:
        fk = frames[keys + ["width", "height"]].drop_duplicates(keys)
        m = df.merge(fk, on=keys, how="left", indicator=True)
        unknown = (m["_merge"] == "left_only").to_numpy()
        if unknown.any():
            r = df.iloc[int(np.nonzero(unknown)[0][0])]
            fail(
                unknown,
                f"unknown frame {r['session']} {r['camera']} {r['utime']} (not in the frame "
                "table: check the session name, camera and utime)",
            )
        with np.errstate(invalid="ignore"):
            fail(
                chg & ((box[:, 2] > m["width"].to_numpy()) | (box[:, 3] > m["height"].to_numpy())),
                "box ends outside the image",
            )
    both = df.groupby(keys)["status"].transform("nunique").to_numpy() > 1
    fail(both, "frame is annotated both change and no-change")
    fail(df.duplicated(keep="first").to_numpy(), "duplicate row")
    fail(
        (~chg) & df.duplicated(keys, keep="first").to_numpy(), "duplicate no-change row for a frame"
    )
    return df[COLUMNS].sort_values(keys + ["x1", "y1"], na_position="first").reset_index(drop=True)


def load_annotations(
    path: Path,
    frames: pd.DataFrame | None = None,
    names: pd.DataFrame | None = None,
    skip_sessions: tuple[str, ...] = (),
) -> pd.DataFrame:
    """Read and validate a canonical annotation CSV (UTF-8; errors name the file's own line).

    A CSV of a folder session may name each row's image (an ``image`` column, the path relative
    to the folder, instead of ``session, camera, utime``; method §13.2): ``names`` (the folder
    sessions' file names) give the frame keys (:func:`harness.ingest.names.frames_by_image`,
    ``skip_sessions`` the map's).
    """
    path = check_input(path, "annotation file", AnnotationError)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        at = raw[: err.start].count(b"\n") + 1
        raise AnnotationError(
            f"{path}: line {at}: not UTF-8 text (byte 0x{raw[err.start]:02x}); save the file as "
            "UTF-8"
        ) from None
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader, None)
        rows, lines = [], []
        start = reader.line_num + 1
        for rec in reader:
            if any(f.strip() for f in rec):  # blank lines are skipped, never renumbered
                if len(rec) != len(header or []):
                    raise AnnotationError(
                        f"{path}: line {start}: {len(rec)} fields where the header has "
                        f"{len(header or [])}"
                    )
                rows.append(rec)
                lines.append(start)
            start = reader.line_num + 1  # a quoted newline makes a record span lines
    except csv.Error as err:
        raise AnnotationError(
            f"{path}: line {reader.line_num}: not a readable CSV: {err}"
        ) from None
    if not header or not any(h.strip() for h in header):
        raise AnnotationError(
            f"{path}: the file is empty (expected a header line {','.join(COLUMNS)})"
        )
    df = pd.DataFrame(rows, columns=[h.strip() for h in header], dtype=object)
    for c in ("x1", "y1", "x2", "y2"):
        if c in df.columns:
            df[c] = df[c].map(lambda v: np.nan if str(v).strip() == "" else v)
    if "image" in df.columns and "utime" not in df.columns:
        where = [f"line {n}" for n in lines]
        none = pd.DataFrame(columns=[*FRAME_KEY, "name"])
        df = frames_by_image(df, none if names is None else names, None, skip_sessions,
                             str(path), where)  # fmt: skip
    return validate_annotations(df, frames, str(path), np.asarray(lines, np.int64))


def change_boxes(ann: pd.DataFrame) -> dict[tuple[str, str, int], np.ndarray]:
    """Frame key -> (c, 4) change boxes (c = 0 for no-change frames), for every annotated frame."""
    out: dict[tuple[str, str, int], np.ndarray] = {}
    for key, g in ann.groupby(FRAME_KEY, sort=True):
        b = g.loc[g["status"] == "change", ["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
        out[(str(key[0]), str(key[1]), int(key[2]))] = b.reshape(-1, 4)
    return out


# ---------------------------------------------------------------- importers


def no_change_row(session: str, camera: str, utime: int) -> dict[str, Any]:
    """The annotation row of a frame labelled as holding no change (box columns NaN)."""
    nan = np.nan
    return dict(
        session=session, camera=camera, utime=utime, status="no-change",
        x1=nan, y1=nan, x2=nan, y2=nan, label="",
    )  # fmt: skip

"""The file names of folder sessions' frames (SPEC 13.2): kept through every output, paired by.

A frame read from a folder (images alone, or TUM, KITTI, EuRoC) is named by its image file's path
relative to the session folder; a frame of a log (NCLT, ROS bags, MCAP) has no file name.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from harness.config.schema import SessionConfig
from harness.errors import IngestError
from harness.ingest.folders import FOLDER_FORMATS, frame_names
from harness.ingest.logs import detect_format
from harness.records import FRAME_KEY

NAME_COLUMNS = [*FRAME_KEY, "name"]


def session_names(sessions: Iterable[SessionConfig]) -> pd.DataFrame:
    """``session, camera, utime, name`` of every frame of the folder sessions.

    None for logs, or for a folder no longer there.

    Raises:
        IngestError: a folder's image times cannot be read (one line naming the file).
    """
    parts = []
    for sc in sessions:
        src = Path(sc.source)
        if not src.is_dir():  # a log file, or a source moved after its ingest: no names
            continue
        fmt = sc.format if sc.format != "auto" else detect_format(src)
        if fmt not in FOLDER_FORMATS:
            continue
        try:
            named = frame_names(src, fmt)
        except (ValueError, OSError) as err:
            raise IngestError(f"{src} ({fmt} folder): {err}") from None
        parts.append(
            pd.DataFrame(
                {
                    "session": sc.name,
                    "camera": sc.camera,
                    "utime": pd.Series(list(named), dtype="int64"),
                    "name": list(named.values()),
                }
            )
        )
    if not parts:
        return pd.DataFrame({c: pd.Series(dtype=object) for c in NAME_COLUMNS})
    return pd.concat(parts, ignore_index=True)[NAME_COLUMNS]


def with_names(
    table: pd.DataFrame, names: pd.DataFrame, key: list[str], column: str
) -> pd.DataFrame:
    """``table`` with ``column``: the file name of the frame ``key`` names ("" where none)."""
    n = names.rename(columns=dict(zip(FRAME_KEY, key, strict=True))).rename(
        columns={"name": column}
    )
    out = table.merge(n, on=key, how="left")
    out[column] = out[column].fillna("").astype(str)
    return out

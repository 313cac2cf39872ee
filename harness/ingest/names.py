"""The file names of folder sessions' frames (method §13.2): kept through every output, paired by.

A frame read from a folder (images alone, or TUM, KITTI, EuRoC) is named by its image file's path
relative to the session folder; a frame of a log (NCLT, ROS bags, MCAP) has no file name.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from harness.errors import AnnotationError, IngestError
from harness.ingest.config import SessionConfig
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


def frames_by_image(
    df: pd.DataFrame,
    names: pd.DataFrame,
    frames: pd.DataFrame | None,
    skip_sessions: Iterable[str],
    where: str,
    rows: list[str] | None = None,
) -> pd.DataFrame:
    """Annotation rows that name their image (``image``) with their frame keys (method §13.2).

    ``image`` is the image's path relative to its folder, or its name; it is matched by stem
    (a mask ``0007.png`` names the image ``0007.jpg``) among the folder sessions' frames, leaving
    out ``skip_sessions`` (``harness detect``'s map: annotations are of the new images) unless
    the row names its ``session``. A mask's size (``mask_width``, ``mask_height``) must be its
    image's.

    Raises:
        AnnotationError: an image no folder session holds, one several hold (add a ``session``
            column), or a mask of another size than its image: one line naming ``where`` and the
            row (``rows``: each row's name for the message, else its line in a CSV).
    """
    skip = set(skip_sessions)
    stems = names.assign(stem=[Path(str(n)).stem for n in names["name"]])
    by_stem: dict[str, list[tuple[str, str, int]]] = {}
    for s, c, u, st in stems[[*FRAME_KEY, "stem"]].itertuples(index=False):
        by_stem.setdefault(str(st), []).append((str(s), str(c), int(u)))
    size = frames.set_index(FRAME_KEY)[["width", "height"]] if frames is not None else None
    keys = []
    for i, r in enumerate(df.to_dict("records")):
        at = rows[i] if rows is not None else f"line {i + 2}"
        image = str(r["image"]).strip()
        hits = by_stem.get(Path(image).stem, [])
        if r.get("session"):
            hits = [h for h in hits if h[0] == str(r["session"]).strip()]
        elif len(hits) > 1:
            hits = [h for h in hits if h[0] not in skip] or hits
        if not hits:
            raise AnnotationError(
                f"{where}: {at}: no image named {image!r} in the folder sessions "
                f"({', '.join(sorted(set(names['session']))) or 'none'})"
            )
        if len(hits) > 1:
            raise AnnotationError(
                f"{where}: {at}: the image {image!r} is in several sessions "
                f"({', '.join(h[0] for h in hits)}); add a session column"
            )
        if size is not None and "mask_width" in r and hits[0] in size.index:
            w, h = size.loc[hits[0]]
            if (int(r["mask_width"]), int(r["mask_height"])) != (int(w), int(h)):
                raise AnnotationError(
                    f"{where}: {at}: the mask is {int(r['mask_width'])} x "
                    f"{int(r['mask_height'])} pixels, its image {image!r} {int(w)} x {int(h)}"
                )
        keys.append(hits[0])
    out = df.drop(columns=[c for c in ("image", "session", "camera", "utime") if c in df])
    key = pd.DataFrame(keys, columns=FRAME_KEY, index=df.index)
    return pd.concat([key, out], axis=1)

"""``harness task export``: the localization task a user's own localizer must solve (method §12).

Written into ``OUT/task/`` of a run directory, from the same cache entries (pairs, proposals)
that a later ``harness reproduce --out OUT --import NAME=FILE`` reads, so the rows a user writes
match the run by construction and nothing is recomputed:

- ``queries.parquet`` and ``.csv``: one row per query subimage x reference session (a pair):
  ``q_session, q_camera, q_utime, proposal_method, box_id, x1, y1, x2, y2, r_session, r_camera,
  image, width, height`` (``r_camera``: the pair's reference camera, whose frames to search);
- ``references.parquet`` and ``.csv``: one row per reference subimage (the database):
  ``session, camera, utime, proposal_method, box_id, x1, y1, x2, y2, image, width, height``;
- ``databases.csv``: per reference session x camera x proposal method, ``frames``: the ``L`` of a
  complete ranked list;
- ``schema.md``: the import schema (the rows to write back) and the command that reads them;
- ``task.json``: counts, the cache keys the task comes from, the image mode.

Boxes are in *upright* pixels, x2/y2 exclusive. ``image`` is a path that ``cv2.imread`` opens
as the upright image (``images = "upright"``, the default): frames stored rotated (NCLT's
TIFFs) are written upright as PNG under ``task/images/``; frames already upright are named in
place. With ``images = "source"`` nothing is written and ``image`` is the stored file with a
``rotation`` column (``none``, ``cw``, ``ccw``, ``180``: ``cv2.rotate`` turns it upright), for
logs too large to copy.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import pandas as pd

from harness.imagestore import read_image, split_uri
from harness.records import FRAME_KEY, IMAGE_KEY, QUERY_KEY
from harness.retrieval import import_file, imported
from harness.runtime.cache import atomic_dir, write_json, write_parquet, write_text
from harness.runtime.outdirs import check_replaceable, write_marker

log = logging.getLogger(__name__)

IMAGE_MODES = ("upright", "source")
BOX = import_file.BOX


def _image_columns(frames: pd.DataFrame, tmp: Path, final: Path, mode: str) -> pd.DataFrame:
    """``session, camera, utime, image, width, height`` (+ ``rotation``) of ``frames``."""
    out = frames[["session", "camera", "utime", "width", "height"]].copy()
    paths, rots = [], []
    for s, c, u, uri in zip(
        frames["session"], frames["camera"], frames["utime"], frames["image"], strict=True
    ):
        path, rot = split_uri(str(uri))
        rots.append(rot)
        if mode == "source" or rot == "none":
            paths.append(str(Path(path).resolve()))
            continue
        rel = Path("images") / str(s) / str(c) / f"{int(u)}.png"
        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        rgb = read_image(str(uri))
        if not cv2.imwrite(str(tmp / rel), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{tmp / rel}: could not be written")
        paths.append(str(final / rel))
    out["image"] = paths
    if mode == "source":
        out["rotation"] = rots
    return out


def write_task(
    out: Path,
    frames: pd.DataFrame,
    pairs: pd.DataFrame,
    proposals: dict[str, pd.DataFrame],
    keys: dict[str, Any],
    mode: str = "upright",
) -> dict[str, Any]:
    """Write the task into ``out`` (replaced whole; a user's file inside it is never deleted).

    Args:
        out: The task directory (``OUT/task``).
        frames: The run's frame table (image URIs local to this machine).
        pairs: The run's pairs.
        proposals: Each session's proposals (the run's cache entries).
        keys: The cache keys the task comes from (recorded in ``task.json``).
        mode: ``upright`` or ``source`` (see the module docstring).

    Returns:
        The counts written to ``task.json``.
    """
    if mode not in IMAGE_MODES:
        raise ValueError(f"images must be one of {IMAGE_MODES}, got {mode!r}")
    out = check_replaceable(out, "task", force=True)
    props = pd.concat(list(proposals.values()), ignore_index=True)
    pk = ["session", "camera", "utime", "proposal_method", "box_id", *BOX]
    q = pairs[[*IMAGE_KEY, "r_camera"]].merge(
        props[pk].rename(
            columns={"session": "q_session", "camera": "q_camera", "utime": "q_utime"}
        ),
        on=QUERY_KEY,
        how="inner",
    )
    q = q[[*import_file.KEY[:3], "proposal_method", "box_id", *BOX, "r_session", "r_camera"]]
    q = q.sort_values(import_file.KEY).reset_index(drop=True)
    refs = sorted(set(pairs["r_session"]))
    ref = props.loc[props["session"].isin(refs), pk].sort_values(pk[:5]).reset_index(drop=True)
    used = pd.concat(
        [
            q[QUERY_KEY].set_axis(FRAME_KEY, axis=1),
            ref[FRAME_KEY],
        ]
    ).drop_duplicates()
    fr = frames.merge(used, on=FRAME_KEY, how="inner")
    dbs = (
        ref.groupby(["session", "camera", "proposal_method"], sort=True)["utime"]
        .nunique()
        .reset_index()
        .rename(columns={"session": "r_session", "utime": "frames"})
    )
    with atomic_dir(out) as tmp:
        img = _image_columns(fr, tmp, out, mode)
        qi = q.merge(
            img.rename(columns={"session": "q_session", "camera": "q_camera", "utime": "q_utime"}),
            on=QUERY_KEY,
            how="left",
        )
        ri = ref.merge(img, on=FRAME_KEY, how="left")
        for name, df in (("queries", qi), ("references", ri)):
            write_parquet(tmp / f"{name}.parquet", df)
            write_text(tmp / f"{name}.csv", df.to_csv(index=False))
        write_text(tmp / "databases.csv", dbs.to_csv(index=False))
        write_text(tmp / "schema.md", schema_text())
        counts = {
            "query_subimages": len(qi),
            "query_images": len(pairs),
            "reference_subimages": len(ri),
            "frames": len(fr),
            "images": mode,
        }
        write_json(tmp / "task.json", {"counts": counts, "keys": keys})
        write_marker(tmp, "task", record_entries=True)
    log.info("task: %s query subimages, %s reference subimages -> %s", len(qi), len(ri), out)
    return counts


def schema_text() -> str:
    """``schema.md``: what to write back, and the command that reads it."""
    doc = imported.__doc__ or ""
    return (
        "# The rows your localizer writes back\n\n"
        "One row per row of `queries.csv` (a query subimage and the reference session to search),"
        " with its ranked list of reference frames (`references.csv`, that session's frames), "
        "best first. Then:\n\n"
        "    harness reproduce --config CONFIG --out OUT --import NAME=ranks.parquet\n\n"
        "with the same CONFIG and OUT as `harness task export`.\n\n" + doc
    )

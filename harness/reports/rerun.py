"""``harness detect --rerun OUT.rrd``: the run as a recording the Rerun viewer scrubs.

Optional extra ``dbl-harness[rerun]`` (``rerun-sdk``, MIT OR Apache-2.0). What is logged:

- ``world/map``: the map session's trajectory (a static line strip in the ground plane, metres);
- ``world/query``: every query frame's position on the ``utime`` timeline (microseconds, the logs'
  clock) and on ``frame`` (its index), coloured by its change score (blue = low, red = high, over
  the run's range), plus the whole query trajectory as a static line, coloured the same way;
- ``camera/<name>/image``: the query frame (JPEG), with ``changes`` (the change boxes, labelled by
  their LoC) under it, and ``camera/<name>/loc``: the pixel-wise LoC map (float32, NaN where no box
  covers, at most ``LOC_WIDTH`` pixels wide);
- ``detect/score``: the frame's change score as a scalar, to plot against time.

Frames are read one chunk of the detector's cache at a time (the cache's units), so the recording
never holds a session in memory. The recording id is derived from the run's output directory name
and options, so the same run names the same recording.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.errors import ConfigError
from harness.fusion.fuse import loc_map
from harness.imagestore import read_image
from harness.records import FRAME_KEY, QUERY_KEY
from harness.runtime.cache import read_cached_parquet, stable_hash

log = logging.getLogger(__name__)

#: The recording's application id (what ``--rerun`` checks before replacing a file).
APPLICATION = "dbl-harness detect"
#: The LoC map's largest width in the recording (pixels; the frame's own size when smaller).
LOC_WIDTH = 320


def rerun_sdk() -> Any:
    """The ``rerun`` module (rerun-sdk), or a ConfigError saying how to install it."""
    try:
        import rerun as rr
    except ImportError:
        raise ConfigError(
            "--rerun needs the Rerun SDK: pip install 'dbl-harness[rerun]' (rerun-sdk)"
        ) from None
    return rr


def score_colours(scores: np.ndarray) -> np.ndarray:
    """(n, 3) uint8: blue (the lowest score) to red (the highest), linear over the run's range."""
    s = np.asarray(scores, np.float64)
    ok = np.isfinite(s)
    lo, hi = (float(s[ok].min()), float(s[ok].max())) if ok.any() else (0.0, 1.0)
    t = np.where(ok, (s - lo) / (hi - lo) if hi > lo else 0.5, 0.0)
    return np.stack([255 * t, np.zeros_like(t), 255 * (1 - t)], 1).round().astype(np.uint8)


def _log_trajectories(
    rr: Any, rec: Any, frames: pd.DataFrame, map_session: str, fr: pd.DataFrame
) -> None:
    """The map session's trajectory (grey) and each query session's (blue), static."""
    m = frames[frames["session"] == map_session].sort_values(["utime", "camera"])
    m = m.drop_duplicates("utime")
    rec.log(
        "world/map",
        rr.LineStrips3D(
            [np.column_stack([m["x"], m["y"], np.zeros(len(m))]).astype(np.float32)],
            colors=[[160, 160, 160]],
            radii=[0.1],
        ),
        static=True,
    )
    for s, g in fr.groupby("session", sort=True):
        rec.log(
            f"world/query/{s}/trajectory",
            rr.LineStrips3D(
                [np.column_stack([g["x"], g["y"], np.zeros(len(g))]).astype(np.float32)],
                colors=[[90, 90, 200]],
                radii=[0.05],
            ),
            static=True,
        )


def _log_frame(
    rr: Any,
    rec: Any,
    r: pd.Series,
    i: int,
    k: tuple[str, str, int],
    colour: Any,
    b: pd.DataFrame | None,
    g: pd.DataFrame,
) -> int:
    """One query frame at its time: position, score, image, change boxes ``b``, LoC map.

    The LoC map is drawn from the frame's fused qBBs ``g``. Returns the number of boxes logged.
    """
    rec.set_time("utime", sequence=int(k[2]))
    rec.set_time("frame", sequence=i)
    rec.log(
        f"world/query/{k[0]}/frame",
        rr.Points3D([[float(r["x"]), float(r["y"]), 0.0]], colors=[colour], radii=[0.4]),
    )
    rec.log("detect/score", rr.Scalars([float(r["score"])]))
    img = read_image(str(r["image"]))
    h, w = img.shape[:2]
    ok, jpg = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
    if not ok:
        raise ConfigError(f"{r['image']}: the frame could not be encoded for the recording")
    cam = f"camera/{k[1]}"
    rec.log(f"{cam}/image", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
    boxes = b[["x1", "y1", "x2", "y2"]].to_numpy(np.float32) if b is not None else np.zeros((0, 4))
    rec.log(
        f"{cam}/image/changes",
        rr.Boxes2D(
            array=boxes.astype(np.float32),
            array_format=rr.Box2DFormat.XYXY,
            labels=[f"{v:.3g}" for v in (b["score"] if b is not None else [])],
            colors=[[255, 220, 0]],
        ),
    )
    lm = loc_map(
        g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64),
        g["loc"].to_numpy(np.float64),
        w,
        h,
    )
    if w > LOC_WIDTH:
        size = (LOC_WIDTH, max(1, round(h * LOC_WIDTH / w)))
        # nearest: the map is constant per box, and NaN (no box) stays NaN
        lm = cv2.resize(lm, size, interpolation=cv2.INTER_NEAREST)
    rec.log(f"{cam}/loc", rr.DepthImage(lm.astype(np.float32), colormap="turbo"))
    return len(boxes)


def write_recording(
    path: Path,
    frames: pd.DataFrame,
    map_session: str,
    fr: pd.DataFrame,
    dets: pd.DataFrame,
    entries: list[Any],
    recording_id: str,
) -> dict[str, int]:
    """Write ``path`` (an ``.rrd``): map and query trajectories, frames, boxes, LoC maps, scores.

    Args:
        path: the ``.rrd`` to write (its folder must exist).
        frames: the frame table (poses ``x``, ``y``, images).
        map_session: the map session's name.
        fr: one row per query frame: key, ``x``, ``y``, ``image``, ``score``.
        dets: the change boxes (``kind == "detection"``) with their LoC (``score``).
        entries: the detector's cached chunks (each with ``samples.parquet``).
        recording_id: names the recording.

    Returns:
        What was logged: query frames, change boxes, LoC maps.
    """
    rr = rerun_sdk()
    rec = rr.RecordingStream(APPLICATION, recording_id=recording_id)
    rec.set_log_time_enabled(False)  # the logs' own clock only: the same run, the same data
    rec.save(str(path))
    fr = fr.sort_values(["utime", "camera", "session"]).reset_index(drop=True)
    colours = score_colours(fr["score"].to_numpy(np.float64))
    _log_trajectories(rr, rec, frames, map_session, fr)
    index = {
        (str(r.session), str(r.camera), int(r.utime)): i
        for i, r in enumerate(fr[FRAME_KEY].itertuples(index=False))
    }
    det = dets[dets["kind"] == "detection"]
    by_frame = {(str(k[0]), str(k[1]), int(k[2])): g for k, g in det.groupby(FRAME_KEY, sort=False)}
    counts = {"query_frames": 0, "change_boxes": 0, "loc_maps": 0}
    for e in entries:  # one cached chunk at a time
        samples = read_cached_parquet(e.path / "samples.parquet")
        for key, g in samples.groupby(QUERY_KEY, sort=True):
            k = (str(key[0]), str(key[1]), int(key[2]))
            i = index.get(k)
            if i is None:
                continue
            n_boxes = _log_frame(rr, rec, fr.iloc[i], i, k, colours[i], by_frame.get(k), g)
            counts["query_frames"] += 1
            counts["change_boxes"] += n_boxes
            counts["loc_maps"] += 1
    rec.flush()
    rec.disconnect()
    log.info(
        "rerun: wrote %s (%d query frames, %d change boxes, %d LoC maps)",
        path,
        counts["query_frames"],
        counts["change_boxes"],
        counts["loc_maps"],
    )
    return counts


def recording_id(out: Path, options: dict[str, Any]) -> str:
    """The recording's id: the run's folder name and its options (the same run, the same id)."""
    return "dbl-harness-" + stable_hash(Path(out).name, options, length=16)


def check_rerun_target(path: Path) -> None:
    """Refuse a ``--rerun`` path that exists and is not a recording ``harness detect`` wrote.

    Raises:
        ConfigError: the path is a folder, or a file of someone else's (never replaced).
    """
    if path.is_dir():
        raise ConfigError(f"--rerun {path}: is a folder; give the .rrd file to write")
    if not path.exists():
        if not path.parent.is_dir():
            raise ConfigError(f"--rerun {path}: its folder {path.parent} does not exist")
        return
    rr = rerun_sdk()
    from rerun.chunk import RrdReader

    try:
        apps = {s.application_id for s in RrdReader(path).recordings()}
    except Exception:  # an unreadable or foreign file: not ours to replace
        apps = set()
    del rr
    if apps != {APPLICATION}:
        raise ConfigError(
            f"--rerun {path}: exists and is not a recording harness detect wrote; it is never "
            "replaced: remove it or choose another path"
        )


def write_rerun(
    path: Path,
    out: Path,
    frames: pd.DataFrame,
    map_session: str,
    fr: pd.DataFrame,
    dets: pd.DataFrame,
    entries: list[Any],
    options: dict[str, Any],
) -> dict[str, Any]:
    """The run's Rerun recording at ``path``, written beside it and moved into place whole.

    ``options``: the run's options as ``detect.json`` records them (they name the recording).
    """
    check_rerun_target(path)
    fr = fr.merge(frames[[*FRAME_KEY, "x", "y", "image"]], on=FRAME_KEY)
    tmp = path.with_name(f".{path.name}.partial")
    try:
        counts = write_recording(
            tmp,
            frames,
            map_session,
            fr,
            dets,
            entries,
            recording_id(out, options),
        )
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return {"path": str(path), **counts}

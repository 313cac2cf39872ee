"""A session's frame table: rows of stamped frames and poses, drop counts, the atomic write."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from harness.errors import IngestError
from harness.ingest.config import IngestConfig, SessionConfig
from harness.ingest.poses import interpolate
from harness.records import FRAME_COLUMNS, FRAME_SCHEMA
from harness.runtime.cache import write_json, write_parquet


def build_frame_table(
    session: str,
    camera: str,
    img_t: np.ndarray,
    poses: np.ndarray,
    uris: list[str],
    sizes: np.ndarray,
    pose_frame: str = "",
    pose_of: str = "",
) -> pd.DataFrame:
    """One session's frame rows (method §2's frame table) from image times, poses and URIs."""
    df = pd.DataFrame(
        {
            "session": session,
            "camera": camera,
            "utime": img_t.astype(np.int64),
            "x": poses[:, 0],
            "y": poses[:, 1],
            "z": poses[:, 2],
            "roll": poses[:, 3],
            "pitch": poses[:, 4],
            "yaw": poses[:, 5],
            "image": uris,
            "width": sizes[:, 0].astype(np.int32),
            "height": sizes[:, 1].astype(np.int32),
            "pose_frame": pose_frame,
            "pose_of": pose_of,
        },
        columns=FRAME_COLUMNS,
    )
    return df


def finish(
    sc: SessionConfig,
    ic: IngestConfig,
    tmp: Path,
    images: tuple[np.ndarray, list[str], np.ndarray],
    poses: tuple[np.ndarray, np.ndarray],
    report: dict,
) -> pd.DataFrame:
    """Interpolate poses at image times, drop and count, write the frame table and the report.

    ``images``: the images' times, URIs and sizes; ``poses``: the pose times and values.
    """
    img_t, uris, sizes = images
    pose_t, pose_v = poses
    finite = np.isfinite(pose_v).all(axis=1)
    report["dropped"]["non_finite_pose"] = int((~finite).sum())
    pose_t, pose_v = pose_t[finite], pose_v[finite]
    order = np.argsort(pose_t, kind="stable")
    pose_t, pose_v = pose_t[order], pose_v[order]
    uniq = np.concatenate([[True], np.diff(pose_t) > 0]) if len(pose_t) else np.zeros(0, bool)
    report["dropped"]["duplicate_pose_time"] = int((~uniq).sum())
    pose_t, pose_v = pose_t[uniq], pose_v[uniq]
    res = interpolate(pose_t, pose_v, img_t, round(ic.max_pose_gap_s * 1e6))
    report["dropped"].update(res.dropped)
    report["poses_used"] = len(pose_t)
    return write_frames(sc, tmp, img_t, uris, sizes, res.poses, res.keep, report)


def write_frames(
    sc: SessionConfig,
    tmp: Path,
    img_t: np.ndarray,
    uris: list[str],
    sizes: np.ndarray,
    poses: np.ndarray,
    keep: np.ndarray,
    report: dict,
) -> pd.DataFrame:
    """The frame table of the images kept (``poses``: one row per kept image) and the report."""
    pf = report.get("pose_frames", {})
    df = build_frame_table(
        sc.name,
        sc.camera,
        img_t[keep],
        poses,
        [u for u, k in zip(uris, keep, strict=True) if k],
        sizes[keep],
        pf.get("pose_frame", ""),
        pf.get("pose_of", ""),
    )
    report["frames_written"] = len(df)
    if len(img_t) and not len(df):
        raise IngestError(
            f"{sc.source}: none of the {len(img_t)} images got a pose (dropped: "
            f"{report['dropped']}); "
            "check the pose topic (or /tf frames), the time source and [ingest] "
            "max_pose_gap_s / max_tf_gap_s"
        )
    write_parquet(tmp / "frames.parquet", df, schema=FRAME_SCHEMA)
    write_json(tmp / "ingest_report.json", report)
    return df

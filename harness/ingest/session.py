"""Ingest one season log into ``frames.parquet`` + ``ingest_report.json`` (+ an image store)."""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd

from ..cache import atomic_dir, write_json, write_parquet
from ..config import IngestConfig, SessionConfig
from ..errors import CorruptLogError, IngestError
from ..imagestore import make_uri, resolve, stored_size, upright_size
from ..outdirs import check_replaceable, write_marker
from ..records import FRAME_COLUMNS, FRAME_SCHEMA
from .images import compressed_kind, compressed_size, decode_problem, raw_to_array, write_raw
from .logs import choose_topics, detect_format, list_topics, stream, uri_safe_path
from .poses import check_monotonic, interpolate, pose_rows, stamp_us

log = logging.getLogger(__name__)


def _frames_table(session: str, camera: str, img_t: np.ndarray, poses: np.ndarray, uris: list[str], sizes: np.ndarray) -> pd.DataFrame:
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
        },
        columns=FRAME_COLUMNS,
    )
    return df


def _finish(
    sc: SessionConfig, ic: IngestConfig, tmp: Path, img_t: np.ndarray, uris: list[str], sizes: np.ndarray,
    pose_t: np.ndarray, pose_v: np.ndarray, report: dict,
) -> pd.DataFrame:
    """Interpolate poses at image times, drop and count, write the frame table and the report."""
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
    keep = res.keep
    df = _frames_table(sc.name, sc.camera, img_t[keep], res.poses, [u for u, k in zip(uris, keep, strict=True) if k], sizes[keep])
    report["frames_written"] = len(df)
    report["poses_used"] = len(pose_t)
    if len(img_t) and not len(df):
        raise IngestError(
            f"{sc.source}: none of the {len(img_t)} images got a pose (dropped: {report['dropped']}); "
            "check the pose topic, the time source and [ingest] max_pose_gap_s"
        )
    write_parquet(tmp / "frames.parquet", df, schema=FRAME_SCHEMA)
    write_json(tmp / "ingest_report.json", report)
    return df


def _ingest_log(sc: SessionConfig, ic: IngestConfig, fmt: str, tmp: Path, report: dict) -> pd.DataFrame:
    src = Path(sc.source)
    with uri_safe_path(src) as readable:
        try:
            return _ingest_log_from(sc, ic, fmt, tmp, report, src, readable)
        except CorruptLogError as err:
            if readable == src:
                raise
            raise CorruptLogError(src, err.messages_read, err.detail.replace(str(readable), str(src)), ic.salvage) from None


def _ingest_log_from(sc: SessionConfig, ic: IngestConfig, fmt: str, tmp: Path, report: dict, src: Path, readable: Path) -> pd.DataFrame:
    """Ingest a ROS log; ``readable`` is ``src`` or a link to it that rosbags can open."""
    topics = list_topics(readable, fmt, salvage=ic.salvage)
    image_topic, pose_topic = choose_topics(topics, sc.image_topic, sc.pose_topic, str(src))
    report["topics"] = {"image": image_topic, "pose": pose_topic, "available": {t: v[0] for t, v in sorted(topics.items())}}
    store = tmp / "images" / sc.camera
    store.mkdir(parents=True)
    read: Counter[str] = Counter()
    img_t: list[int] = []
    uris: list[str] = []
    sizes: list[tuple[int, int]] = []
    seen: set[int] = set()
    rows_by_child: dict[str | None, list[tuple]] = {}
    dropped = report["dropped"]
    stats: dict[str, int] = {}
    try:
        for m in stream(readable, fmt, (image_topic, pose_topic), salvage=ic.salvage):
            read[m.topic] += 1
            where = f"{src}: {m.topic} message {read[m.topic]}"
            if m.topic == image_topic:
                t = stamp_us(m.msg.header) if ic.time_source == "header" else m.log_ns // 1000  # type: ignore[attr-defined]
                if img_t and t < img_t[-1]:
                    raise IngestError(f"{where}: image time stamps are not monotonic: utime {t} comes after utime {img_t[-1]}")
                if t in seen:
                    dropped["duplicate_image_time"] = dropped.get("duplicate_image_time", 0) + 1
                    continue
                seen.add(t)
                if m.msgtype.endswith("CompressedImage"):
                    kind = compressed_kind(m.msg, where)
                    data = bytes(np.asarray(m.msg.data, dtype=np.uint8))  # type: ignore[attr-defined]
                    w, h = compressed_size(data, where)
                    if ic.verify_images:
                        problem = decode_problem(data)
                        if problem:
                            log.warning("%s: dropped: %s", where, problem)
                            dropped["corrupt_image"] = dropped.get("corrupt_image", 0) + 1
                            continue
                    name = f"{t}.{kind}"
                    (store / name).write_bytes(data)
                else:
                    arr = raw_to_array(m.msg, where)
                    h, w = arr.shape[:2]
                    name = write_raw(store / str(t), arr, ic.store_format).name
                img_t.append(t)
                uris.append(f"images/{sc.camera}/{name}")
                sizes.append((w, h))
            else:
                tf_child = sc.tf_child_frame
                num = read[m.topic]
                if m.msgtype == "tf2_msgs/msg/TFMessage":
                    for tr in m.msg.transforms:  # type: ignore[attr-defined]
                        if tf_child in (None, tr.child_frame_id):
                            rows_by_child.setdefault(tr.child_frame_id, []).extend(
                                (*r, num) for r in pose_rows(_OneTf(tr), m.msgtype, m.log_ns // 1000, ic.time_source, tf_child, where, stats))
                else:
                    rows_by_child.setdefault(None, []).extend(
                        (*r, num) for r in pose_rows(m.msg, m.msgtype, m.log_ns // 1000, ic.time_source, None, where, stats))
    except CorruptLogError as err:
        if not ic.salvage:
            raise
        report["salvaged"] = {"messages_read": err.messages_read, "detail": err.detail}
        log.warning("%s: salvaging %d messages read before the damage (%s)", src, err.messages_read, err.detail)
    report["messages_read"] = dict(sorted(read.items()))
    if sum(read.values()) == 0:
        raise IngestError(f"{src}: the log has no message on {image_topic} or {pose_topic} (empty log)")
    if not img_t:
        raise IngestError(f"{src}: no image message on {image_topic}")
    rows = _pose_rows_for(rows_by_child, sc, src)
    if not rows:
        raise IngestError(f"{src}: no pose message on {pose_topic}")
    pose_arr = np.array(rows, dtype=np.float64)
    pose_t = pose_arr[:, 0].astype(np.int64)
    check_monotonic(pose_t, f"{src}: {pose_topic}", "pose", numbers=pose_arr[:, 7].astype(np.int64))
    report["normalised"] = {"quaternion_normalised": stats.get("quaternion_normalised", 0)}
    return _finish(sc, ic, tmp, np.array(img_t, np.int64), uris, np.array(sizes, np.int64), pose_t, pose_arr[:, 1:7], report)


class _OneTf:
    """A TFMessage view holding one transform (so pose_rows handles one child at a time)."""

    def __init__(self, tr: object) -> None:
        self.transforms = [tr]


def _pose_rows_for(rows_by_child: dict[str | None, list[tuple]], sc: SessionConfig, src: Path) -> list[tuple]:
    if None in rows_by_child:
        return rows_by_child[None]
    children = sorted(c for c in rows_by_child if rows_by_child[c])
    if sc.tf_child_frame is not None:
        if sc.tf_child_frame not in rows_by_child:
            raise IngestError(f"{src}: /tf has no transform to child frame {sc.tf_child_frame!r}; child frames: {children}")
        return rows_by_child[sc.tf_child_frame]
    if len(children) > 1:
        raise IngestError(f"{src}: /tf holds several child frames {children}; choose one with tf_child_frame")
    return rows_by_child[children[0]] if children else []


def read_nclt_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """NCLT ground truth ``utime, x, y, z, roll, pitch, yaw`` (no header).

    Returns:
        (utime (n,), values (n, 6), number of rows skipped because they hold NaN or infinity,
        1-based line number of each kept row).

    Raises:
        IngestError: A row has the wrong number of fields or a non-numeric value (names the line).
    """
    if not path.exists():
        raise IngestError(f"{path}: ground-truth file not found")
    times, vals, lines, nan_rows = [], [], [], 0
    with open(path) as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.strip()
            if not line:
                continue
            parts = line.split(",")
            if len(parts) != 7:
                raise IngestError(f"{path}: line {lineno}: expected 7 fields (utime,x,y,z,roll,pitch,yaw), got {len(parts)}")
            try:
                t0 = float(parts[0])
                t = int(t0) if math.isfinite(t0) else 0
                v = [float(p) for p in parts[1:]]
            except ValueError:
                raise IngestError(f"{path}: line {lineno}: non-numeric value in {line!r}") from None
            if not all(math.isfinite(x) for x in v) or not math.isfinite(float(parts[0])):
                nan_rows += 1
                continue
            times.append(t)
            vals.append(v)
            lines.append(lineno)
    if not times:
        raise IngestError(f"{path}: no valid ground-truth row")
    t_arr = np.array(times, np.int64)
    line_arr = np.array(lines, np.int64)
    check_monotonic(t_arr, str(path), "ground-truth", numbers=line_arr, unit="line")
    return t_arr, np.array(vals, np.float64), nan_rows, line_arr


def _ingest_nclt(sc: SessionConfig, ic: IngestConfig, tmp: Path, report: dict) -> pd.DataFrame:
    root = Path(sc.source)
    img_dir = root / "images" / sc.name / "lb3" / sc.camera
    if not img_dir.is_dir():
        avail = sorted(p.name for p in (root / "images" / sc.name / "lb3").glob("Cam*")) if (root / "images" / sc.name / "lb3").is_dir() else []
        raise IngestError(f"{img_dir}: no such NCLT image directory (cameras found for {sc.name}: {avail or 'none'})")
    gt_path = root / "ground_truth" / f"groundtruth_{sc.name}.csv"
    pose_t, pose_v, nan_rows, _ = read_nclt_groundtruth(gt_path)
    report["dropped"]["groundtruth_non_finite_rows"] = nan_rows
    report["messages_read"] = {"ground_truth_rows": len(pose_t) + nan_rows}
    files = []
    bad = 0
    for p in img_dir.iterdir():
        if p.suffix.lower() not in (".tiff", ".tif", ".png", ".jpg"):
            continue
        try:
            files.append((int(p.stem), p))
        except ValueError:
            bad += 1
    report["dropped"]["bad_image_name"] = bad
    if not files:
        raise IngestError(f"{img_dir}: no images")
    files.sort()
    report["messages_read"]["images"] = len(files)
    rot = ic.nclt_rotation
    sizes, uris = [], []
    for _, p in files:
        w, h = stored_size(p)
        sizes.append(upright_size(w, h, rot))
        uris.append(make_uri(p.resolve(), rot))
    img_t = np.array([t for t, _ in files], np.int64)
    return _finish(sc, ic, tmp, img_t, uris, np.array(sizes, np.int64), pose_t, pose_v, report)


def ingest_session(sc: SessionConfig, ic: IngestConfig, out: Path, force: bool = False) -> dict:
    """Ingest one session into ``out`` (written atomically; an earlier ``out`` survives a failure).

    ``out`` must be new or empty, or (with ``force``) an earlier ingest output of the harness;
    anything else is refused, never replaced.

    Returns:
        The ingest report (also written to ``out/ingest_report.json``).

    Raises:
        IngestError: Bad input (the message names the file, message or row).
    """
    src = Path(sc.source)
    fmt = detect_format(src) if sc.format == "auto" else sc.format
    if fmt not in ("nclt", "ros1", "ros2", "mcap"):
        raise IngestError(f"{src}: unknown format {fmt!r}")
    out = check_replaceable(Path(out), "ingest", force)
    t0 = time.perf_counter()
    report: dict = {"session": sc.name, "camera": sc.camera, "source": str(src), "format": fmt, "dropped": {}}
    with atomic_dir(Path(out)) as tmp:
        if fmt == "nclt":
            df = _ingest_nclt(sc, ic, tmp, report)
        else:
            df = _ingest_log(sc, ic, fmt, tmp, report)
        report["seconds"] = round(time.perf_counter() - t0, 3)
        write_json(tmp / "ingest_report.json", report)
        write_marker(tmp, "ingest")
    log.info("ingest %s (%s): read %s, wrote %d frames, dropped %s", sc.name, fmt, report.get("messages_read"), len(df), {k: v for k, v in report["dropped"].items() if v})
    return report


def load_frames(path: Path) -> pd.DataFrame:
    """Read a ``frames.parquet`` and make its image URIs absolute."""
    path = Path(path)
    df = pd.read_parquet(path)
    base = path.parent
    df["image"] = [resolve(u, base) for u in df["image"]]
    return df

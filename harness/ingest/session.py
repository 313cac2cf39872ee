"""Ingest one season log into ``frames.parquet`` + ``ingest_report.json`` (+ an image store)."""

from __future__ import annotations

import json
import logging
import math
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from ..cache import atomic_dir, write_json, write_parquet
from ..config import IngestConfig, SessionConfig
from ..errors import CorruptLogError, IngestError
from ..imagestore import (
    DATA_PREFIX,
    OUT_PREFIX,
    local_uri,
    make_uri,
    pixel_limit,
    portable_uri,
    resolve,
    stored_size,
    upright_size,
)
from ..inputs import check_input, read_text
from ..outdirs import check_replaceable, write_marker
from ..records import FRAME_COLUMNS, FRAME_SCHEMA
from .images import compressed_kind, compressed_size, decode_problem, raw_to_array, write_raw
from .logs import (
    choose_topics,
    detect_format,
    known_formats,
    list_topics,
    stream,
    uri_safe_path,
)
from .poses import (
    POSE_TYPES,
    check_monotonic,
    euler_from_quaternion,
    interpolate,
    pose_rows,
    stamp_us,
)
from .tf import TfTree

log = logging.getLogger(__name__)


def _frames_table(
    session: str,
    camera: str,
    img_t: np.ndarray,
    poses: np.ndarray,
    uris: list[str],
    sizes: np.ndarray,
    pose_frame: str = "",
    pose_of: str = "",
) -> pd.DataFrame:
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


def _finish(
    sc: SessionConfig,
    ic: IngestConfig,
    tmp: Path,
    img_t: np.ndarray,
    uris: list[str],
    sizes: np.ndarray,
    pose_t: np.ndarray,
    pose_v: np.ndarray,
    report: dict,
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
    report["poses_used"] = len(pose_t)
    return _write_frames(sc, tmp, img_t, uris, sizes, res.poses, res.keep, report)


def _write_frames(
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
    df = _frames_table(
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


def _ingest_log(
    sc: SessionConfig, ic: IngestConfig, fmt: str, tmp: Path, report: dict
) -> pd.DataFrame:
    src = Path(sc.source)
    with uri_safe_path(src) as readable:
        try:
            return _ingest_log_from(sc, ic, fmt, tmp, report, src, readable)
        except CorruptLogError as err:
            if readable == src:
                raise
            raise CorruptLogError(
                src, err.messages_read, err.detail.replace(str(readable), str(src)), ic.salvage
            ) from None


TF_TYPE = "tf2_msgs/msg/TFMessage"


def _is_static_tf(topic: str) -> bool:
    return topic.rstrip("/").split("/")[-1] == "tf_static"


def _pose_mode(sc: SessionConfig, topics: dict[str, tuple[str, int]], where: str) -> str:
    """``tf`` (poses composed through the tf tree) or ``topic`` (one pose topic, as it is)."""
    tf_topics = [t for t, (typ, _) in topics.items() if typ == TF_TYPE]
    if sc.pose_topic is not None:
        if sc.pose_topic in topics and topics[sc.pose_topic][0] == TF_TYPE:
            return "tf"
        return "topic"
    if sc.fixed_frame or sc.camera_frame:
        if not tf_topics:
            raise IngestError(
                f"{where}: fixed_frame / camera_frame are set, but the log has no "
                "tf2_msgs/TFMessage topic"
            )
        return "tf"
    others = [t for t, (typ, _) in topics.items() if typ in POSE_TYPES and typ != TF_TYPE]
    return "topic" if others or not tf_topics else "tf"


def _ingest_log_from(
    sc: SessionConfig,
    ic: IngestConfig,
    fmt: str,
    tmp: Path,
    report: dict,
    src: Path,
    readable: Path,
) -> pd.DataFrame:
    """Ingest a ROS log; ``readable`` is ``src`` or a link to it that rosbags can open."""
    topics = list_topics(readable, fmt, salvage=ic.salvage)
    mode = _pose_mode(sc, topics, str(src))
    if mode == "tf":
        no_tf = {t: v for t, v in topics.items() if v[0] != TF_TYPE}
        image_topic, _ = choose_topics(
            no_tf | {"__tf__": (TF_TYPE, 0)}, sc.image_topic, "__tf__", str(src)
        )
        pose_topics = tuple(sorted(t for t, (typ, _) in topics.items() if typ == TF_TYPE))
    else:
        no_tf = {t: v for t, v in topics.items() if v[0] != TF_TYPE or t == sc.pose_topic}
        image_topic, pose_topic = choose_topics(no_tf, sc.image_topic, sc.pose_topic, str(src))
        pose_topics = (pose_topic,)
    report["topics"] = {
        "image": image_topic,
        "pose": list(pose_topics),
        "pose_source": mode,
        "available": {t: v[0] for t, v in sorted(topics.items())},
    }
    store = tmp / "images" / sc.camera
    store.mkdir(parents=True)
    read: Counter[str] = Counter()
    img_t: list[int] = []
    uris: list[str] = []
    sizes: list[tuple[int, int]] = []
    seen: set[int] = set()
    rows: list[tuple] = []
    tree = TfTree()
    frame_ids: Counter[str] = Counter()
    pose_frame: dict[str, str] = {}
    dropped = report["dropped"]
    stats: dict[str, int] = {}
    try:
        for m in stream(readable, fmt, (image_topic, *pose_topics), salvage=ic.salvage):
            read[m.topic] += 1
            where = f"{src}: {m.topic} message {read[m.topic]}"
            if m.topic == image_topic:
                t = stamp_us(m.msg.header) if ic.time_source == "header" else m.log_ns // 1000
                if img_t and t < img_t[-1]:
                    raise IngestError(
                        f"{where}: image time stamps are not monotonic: utime {t} comes "
                        f"after utime {img_t[-1]}"
                    )
                if t in seen:
                    dropped["duplicate_image_time"] = dropped.get("duplicate_image_time", 0) + 1
                    continue
                seen.add(t)
                frame_ids[str(m.msg.header.frame_id).lstrip("/")] += 1
                if m.msgtype.endswith("CompressedImage"):
                    kind = compressed_kind(m.msg, where)
                    data = bytes(np.asarray(m.msg.data, dtype=np.uint8))
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
            elif mode == "tf":
                static = _is_static_tf(m.topic)
                for tr in m.msg.transforms:
                    tl, q = tr.transform.translation, tr.transform.rotation
                    vals = (tl.x, tl.y, tl.z, q.x, q.y, q.z, q.w)
                    if not all(math.isfinite(v) for v in vals):
                        dropped["non_finite_transform"] = dropped.get("non_finite_transform", 0) + 1
                        tree.touch(str(tr.header.frame_id), str(tr.child_frame_id), static, where)
                        continue
                    parent, child = (
                        str(tr.header.frame_id).lstrip("/"),
                        str(tr.child_frame_id).lstrip("/"),
                    )
                    edge = f"{parent}->{child}"
                    euler_from_quaternion(
                        q.x, q.y, q.z, q.w, f"{where} ({edge})", stats
                    )  # the norm check
                    t = stamp_us(tr.header) if ic.time_source == "header" else m.log_ns // 1000
                    tree.add(
                        str(tr.header.frame_id),
                        str(tr.child_frame_id),
                        t,
                        (tl.x, tl.y, tl.z),
                        (q.x, q.y, q.z, q.w),
                        static,
                        where,
                    )
            else:
                num = read[m.topic]
                if not pose_frame:
                    pose_frame = {
                        "pose_frame": str(m.msg.header.frame_id).lstrip("/"),
                        "pose_of": str(getattr(m.msg, "child_frame_id", "") or m.topic).lstrip("/"),
                    }
                rows.extend(
                    (*r, num)
                    for r in pose_rows(
                        m.msg, m.msgtype, m.log_ns // 1000, ic.time_source, None, where, stats
                    )
                )
    except CorruptLogError as err:
        if not ic.salvage:
            raise
        report["salvaged"] = {"messages_read": err.messages_read, "detail": err.detail}
        log.warning(
            "%s: salvaging %d messages read before the damage (%s)",
            src,
            err.messages_read,
            err.detail,
        )
    report["messages_read"] = dict(sorted(read.items()))
    if sum(read.values()) == 0:
        raise IngestError(
            f"{src}: the log has no message on {image_topic} or {', '.join(pose_topics)} "
            "(empty log)"
        )
    if not img_t:
        raise IngestError(f"{src}: no image message on {image_topic}")
    report["normalised"] = {"quaternion_normalised": stats.get("quaternion_normalised", 0)}
    img_arr, size_arr = np.array(img_t, np.int64), np.array(sizes, np.int64)
    if mode == "tf":
        return _finish_tf(sc, ic, tmp, img_arr, uris, size_arr, tree, frame_ids, report, src)
    if not rows:
        raise IngestError(f"{src}: no pose message on {pose_topics[0]}")
    report["pose_frames"] = pose_frame
    pose_arr = np.array(rows, dtype=np.float64)
    pose_t = pose_arr[:, 0].astype(np.int64)
    check_monotonic(
        pose_t, f"{src}: {pose_topics[0]}", "pose", numbers=pose_arr[:, 7].astype(np.int64)
    )
    return _finish(sc, ic, tmp, img_arr, uris, size_arr, pose_t, pose_arr[:, 1:7], report)


def _finish_tf(
    sc: SessionConfig,
    ic: IngestConfig,
    tmp: Path,
    img_t: np.ndarray,
    uris: list[str],
    sizes: np.ndarray,
    tree: TfTree,
    frame_ids: Counter[str],
    report: dict,
    src: Path,
) -> pd.DataFrame:
    """Camera poses composed through the tf tree at the image times (SPEC section 3)."""
    if not tree.edges:
        raise IngestError(f"{src}: the /tf topics hold no transform")
    frames = tree.frames()
    roots = tree.roots()
    if sc.fixed_frame:
        fixed = sc.fixed_frame.lstrip("/")
        if fixed not in frames:
            raise IngestError(
                f"{src}: fixed_frame {fixed!r} is not in the /tf tree; frames: {sorted(frames)}"
            )
    elif len(roots) == 1:
        fixed = roots[0]
    elif not roots:
        raise IngestError(
            f"{src}: the /tf tree has no root: its transforms form a loop ("
            + ", ".join(sorted(e.name for e in tree.edges.values()))
            + "); a tf tree has one parent per frame and no cycle"
        )
    else:
        raise IngestError(
            f"{src}: the /tf tree has several roots {roots}; choose the frame poses are "
            "expressed in with fixed_frame"
        )
    named = sc.camera_frame or sc.tf_child_frame
    if named:
        camera, why = named.lstrip("/"), "camera_frame"
    elif len(frame_ids) == 1:
        camera, why = next(iter(frame_ids)), "the images' header.frame_id"
    else:
        raise IngestError(
            f"{src}: the images name several frames {sorted(frame_ids)}; choose one with "
            "camera_frame"
        )
    if camera not in frames:
        below = ", ".join(sorted(e.child for e in tree.edges.values() if e.parent == fixed))
        raise IngestError(
            f"{src}: the camera frame {camera!r} ({why}) is not in the /tf tree; frames: "
            f"{sorted(frames)}; "
            f"set camera_frame (children of {fixed}: {below})"
        )
    path = tree.path(fixed, camera)
    gaps, transforms = {}, {}
    for e in tree.edges.values():
        interval = e.median_interval_s()
        gap_s = ic.max_pose_gap_s if interval <= ic.max_pose_gap_s else ic.max_tf_gap_s
        gaps[e.name] = round(gap_s * 1e6)
        transforms[e.name] = {
            "static": e.static,
            "transforms": len(e.times),
            "on_path": e in path,
            "median_interval_s": None
            if e.static or not math.isfinite(interval)
            else round(interval, 4),
            "gap_s": None if e.static else gap_s,
        }
    trans, rot, ok, drops = tree.lookup(fixed, camera, img_t, gaps)
    for edge, reasons in drops.items():
        for reason, count in reasons.items():
            report["dropped"][f"tf {edge}: {reason}"] = count
    report["tf"] = {
        "fixed_frame": fixed,
        "camera_frame": camera,
        "path": [e.name for e in path],
        "roots": roots,
        "transforms": transforms,
    }
    report["pose_frames"] = {"pose_frame": fixed, "pose_of": camera}
    if len(img_t) and not ok.any():
        raise IngestError(
            f"{src}: none of the {len(img_t)} images got a pose from /tf ({fixed} -> "
            f"{camera}); dropped: {report['dropped']}; "
            "check the time source and [ingest] max_pose_gap_s / max_tf_gap_s"
        )
    eul = np.array([euler_from_quaternion(*q) for q in rot[ok]]).reshape(-1, 3)
    poses = np.column_stack([trans[ok], eul])
    return _write_frames(sc, tmp, img_t, uris, sizes, poses, ok, report)


def read_nclt_groundtruth(
    path: Path, salvage: bool = False, cut: list[int] | None = None
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """NCLT ground truth ``utime, x, y, z, roll, pitch, yaw`` (no header).

    Returns:
        (utime (n,), values (n, 6), number of rows skipped because they hold NaN or infinity,
        1-based line number of each kept row).

    With ``salvage``, a damaged *last* line (a log cut while it was written) is dropped and
    counted in ``cut[0]``; a damaged line anywhere else is still an error.

    Raises:
        IngestError: A row has the wrong number of fields or a non-numeric value (names the line).
    """
    cut = cut if cut is not None else [0]
    text = read_text(path, "ground-truth file", IngestError)
    times, vals, lines, nan_rows = [], [], [], 0
    rows = text.splitlines()
    last = max((i for i, r in enumerate(rows, 1) if r.strip()), default=0)
    for lineno, line in enumerate(rows, 1):
        line = line.strip()
        if not line:
            continue
        parts = line.split(",")
        problem = None
        if len(parts) != 7:
            problem = f"expected 7 fields (utime,x,y,z,roll,pitch,yaw), got {len(parts)}"
        else:
            try:
                t0 = float(parts[0])
                t = int(t0) if math.isfinite(t0) else 0
                v = [float(p) for p in parts[1:]]
            except ValueError:
                problem = f"non-numeric value in {line!r}"
        if problem is not None:
            if salvage and lineno == last:  # a log cut while it was written: keep what precedes
                cut[0] += 1
                continue
            hint = " (the last line: --salvage keeps the rows before it)" if lineno == last else ""
            raise IngestError(f"{path}: line {lineno}: {problem}{hint}")
        if not all(math.isfinite(x) for x in v) or not math.isfinite(t0):
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
        avail = (
            sorted(p.name for p in (root / "images" / sc.name / "lb3").glob("Cam*"))
            if (root / "images" / sc.name / "lb3").is_dir()
            else []
        )
        raise IngestError(
            f"{img_dir}: no such NCLT image directory (cameras found for {sc.name}: "
            f"{avail or 'none'})"
        )
    gt_path = root / "ground_truth" / f"groundtruth_{sc.name}.csv"
    cut = [0]
    pose_t, pose_v, nan_rows, _ = read_nclt_groundtruth(gt_path, ic.salvage, cut)
    report["dropped"]["groundtruth_non_finite_rows"] = nan_rows
    if cut[0]:
        report["dropped"]["groundtruth_cut_last_line"] = cut[0]
        report["salvaged"] = True
    report["pose_frames"] = {
        "pose_frame": "nclt_world",
        "pose_of": "body",
    }  # NCLT ground truth: the robot body, not the camera
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
    files.sort()  # by utime, then path: of two files with one utime (.png, .tiff) the first is kept
    uniq = [f for i, f in enumerate(files) if i == 0 or f[0] != files[i - 1][0]]
    report["dropped"]["duplicate_image_time"] = len(files) - len(uniq)
    files = uniq
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
    check_input(src, f"log of session {sc.name}", IngestError, directory=src.is_dir())
    fmt = detect_format(src) if sc.format == "auto" else sc.format
    if fmt not in known_formats():
        raise IngestError(f"{src}: unknown format {fmt!r}; known: {list(known_formats())}")
    out = check_replaceable(Path(out), "ingest", force)
    t0 = time.perf_counter()
    report: dict = {
        "session": sc.name,
        "camera": sc.camera,
        "source": str(src),
        "format": fmt,
        "dropped": {},
    }
    with atomic_dir(Path(out)) as tmp, pixel_limit(ic.max_image_pixels):
        if fmt == "nclt":
            df = _ingest_nclt(sc, ic, tmp, report)
        else:
            df = _ingest_log(sc, ic, fmt, tmp, report)
        report["seconds"] = round(time.perf_counter() - t0, 3)
        write_json(tmp / "ingest_report.json", report)
        write_marker(tmp, "ingest", record_entries=True)
    log.info(
        "ingest %s (%s): read %s, wrote %d frames, dropped %s",
        sc.name,
        fmt,
        report.get("messages_read"),
        len(df),
        {k: v for k, v in report["dropped"].items() if v},
    )
    return report


def load_frames(path: Path) -> pd.DataFrame:
    """Read a ``frames.parquet`` and make its image URIs absolute.

    An ingest output's table holds paths relative to itself; a run's frame table
    (``OUT/cache/frames/<key>/frames.parquet``) holds ``{out}/`` and ``{data_root}/`` URIs, resolved
    against the run directory and the data root its ``run.json`` records.

    Raises:
        IngestError: The file is missing, not a frame table, or a run's table whose run
            directory or data root cannot be found.
    """
    path = check_input(path, "frame table", IngestError)
    try:
        df = pd.read_parquet(path)
    except (OSError, ValueError, pa.ArrowException) as err:
        raise IngestError(f"{path}: not a readable parquet frame table ({err})") from None
    miss = [c for c in ("session", "camera", "utime", "image") if c not in df.columns]
    if miss:
        raise IngestError(f"{path}: not a frame table (no column(s) {miss})")
    base = path.parent
    uris = [str(u) for u in df["image"]]
    if any(u.startswith((OUT_PREFIX, DATA_PREFIX)) for u in uris):
        out, root = _run_of(path)
        uris = [local_uri(u, out, root) for u in uris]
    df["image"] = [resolve(u, base) for u in uris]
    return df


def _run_of(path: Path) -> tuple[Path, Path]:
    """The run directory and data root of a run's cached frame table."""
    run = next((d for d in Path(path).resolve().parents if (d / "run.json").is_file()), None)
    if run is None:
        raise IngestError(
            f"{path}: a run's frame table, but no run.json above it names its data root; pass "
            "the frame table of a finished run (OUT/cache/frames/<key>/frames.parquet)"
        )
    try:
        root = json.loads((run / "run.json").read_text())["config"]["data_root"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise IngestError(f"{run / 'run.json'}: unreadable ({err})") from None
    return run, Path(root)


def combine_frames(
    ingest_dirs: list[Path],
    out: Path,
    data_root: Path,
    tmp: Path,
    sources: list[str] | None = None,
) -> dict[str, int]:
    """The frame table of a run: every session's ``frames.parquet``.

    Sorted by session, camera, utime.

    Image URIs are stored relative to ``out`` or ``data_root`` (``{out}/...``, ``{data_root}/...``),
    so a run directory or data root can move.

    Args:
        ingest_dirs: The sessions' ingest entries.
        out: The run directory.
        data_root: The data root of the config.
        tmp: The frames entry's directory (``frames.parquet`` is written there).
        sources: Each session's source now; an ingest entry made before the data root moved
            (its key is the same: keys name sources relative to the data root) names images in
            place under the old source, and those paths are moved along.

    Returns:
        ``{"frames": number of frames}``.
    """
    parts = []
    for i, p in enumerate(ingest_dirs):
        df = load_frames(p / "frames.parquet")
        if sources is not None:
            old = str(json.loads((p / "ingest_report.json").read_text()).get("source", ""))
            new = str(Path(sources[i]).resolve())
            if old and old != new:
                df["image"] = [
                    new + u[len(old) :] if u.startswith(old + "/") else u for u in df["image"]
                ]
        parts.append(df)
    df = pd.concat(parts, ignore_index=True)
    df["image"] = [portable_uri(u, out, data_root) for u in df["image"]]
    write_parquet(
        tmp / "frames.parquet", df.sort_values(["session", "camera", "utime"]), schema=FRAME_SCHEMA
    )
    return {"frames": len(df)}

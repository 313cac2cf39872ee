"""Ingest one ROS1/ROS2/MCAP/folder log: topics, images, poses or a tf tree, the frame table."""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness.errors import CorruptLogError, IngestError
from harness.ingest.config import IngestConfig, SessionConfig
from harness.ingest.frame_table import finish, write_frames
from harness.ingest.images import (
    compressed_kind,
    compressed_size,
    decode_problem,
    raw_to_array,
    write_raw,
)
from harness.ingest.log_types import uri_safe_path
from harness.ingest.logs import choose_topics, list_topics, stream
from harness.ingest.poses import (
    POSE_TYPES,
    check_monotonic,
    euler_from_quaternion,
    pose_rows,
    stamp_us,
)
from harness.ingest.tf import TfTree

log = logging.getLogger(__name__)


def ingest_log(
    sc: SessionConfig, ic: IngestConfig, fmt: str, tmp: Path, report: dict
) -> pd.DataFrame:
    """The frame table of one log session (format ``fmt``), images written under ``tmp``."""
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


def _pose_mode(sc: SessionConfig, topics: dict[str, tuple[str, int]], where: str, fmt: str) -> str:
    """How the frames get poses: ``tf``, ``topic`` or ``none``.

    ``tf``: composed through the tf tree; ``topic``: one pose topic, as it is; ``none``: a folder
    of images alone (method §13.2), whose frames carry no pose.
    """
    if fmt == "images":
        return "none"
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


def _choose(
    sc: SessionConfig, topics: dict, src: Path, fmt: str, report: dict
) -> tuple[str, str, tuple[str, ...]]:
    """(pose mode, image topic, pose topics) of a log; written into ``report["topics"]``."""
    mode = _pose_mode(sc, topics, str(src), fmt)
    if mode == "none":
        image_topic, _ = choose_topics(
            topics | {"__none__": (next(iter(POSE_TYPES)), 0)}, sc.image_topic, "__none__", str(src)
        )
        pose_topics: tuple[str, ...] = ()
    elif mode == "tf":
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
    return mode, image_topic, pose_topics


@dataclass
class _LogReading:
    """What one pass over a log's messages gathers: images, poses or transforms, counts."""

    ic: IngestConfig
    store: Path
    camera: str
    dropped: dict
    read: Counter[str] = field(default_factory=Counter)
    img_t: list[int] = field(default_factory=list)
    uris: list[str] = field(default_factory=list)
    sizes: list[tuple[int, int]] = field(default_factory=list)
    seen: set[int] = field(default_factory=set)
    rows: list[tuple] = field(default_factory=list)
    tree: TfTree = field(default_factory=TfTree)
    frame_ids: Counter[str] = field(default_factory=Counter)
    pose_frame: dict[str, str] = field(default_factory=dict)
    stats: dict[str, int] = field(default_factory=dict)

    def image(self, m: Any, where: str) -> None:
        """An image message: stored as it came (compressed) or in ``store_format`` (raw)."""
        ic, dropped = self.ic, self.dropped
        t = stamp_us(m.msg.header) if ic.time_source == "header" else m.log_ns // 1000
        if self.img_t and t < self.img_t[-1]:
            raise IngestError(
                f"{where}: image time stamps are not monotonic: utime {t} comes "
                f"after utime {self.img_t[-1]}"
            )
        if t in self.seen:
            dropped["duplicate_image_time"] = dropped.get("duplicate_image_time", 0) + 1
            return
        self.seen.add(t)
        self.frame_ids[str(m.msg.header.frame_id).lstrip("/")] += 1
        if m.msgtype.endswith("CompressedImage"):
            kind = compressed_kind(m.msg, where)
            data = bytes(np.asarray(m.msg.data, dtype=np.uint8))
            w, h = compressed_size(data, where)
            if ic.verify_images:
                problem = decode_problem(data)
                if problem:
                    log.warning("%s: dropped: %s", where, problem)
                    dropped["corrupt_image"] = dropped.get("corrupt_image", 0) + 1
                    return
            name = f"{t}.{kind}"
            (self.store / name).write_bytes(data)
        else:
            arr = raw_to_array(m.msg, where)
            h, w = arr.shape[:2]
            name = write_raw(self.store / str(t), arr, ic.store_format).name
        self.img_t.append(t)
        self.uris.append(f"images/{self.camera}/{name}")
        self.sizes.append((w, h))

    def transforms(self, m: Any, where: str) -> None:
        """A tf message: each finite transform into the tree (non-finite ones counted)."""
        static = _is_static_tf(m.topic)
        for tr in m.msg.transforms:
            tl, q = tr.transform.translation, tr.transform.rotation
            vals = (tl.x, tl.y, tl.z, q.x, q.y, q.z, q.w)
            if not all(math.isfinite(v) for v in vals):
                self.dropped["non_finite_transform"] = (
                    self.dropped.get("non_finite_transform", 0) + 1
                )
                self.tree.touch(str(tr.header.frame_id), str(tr.child_frame_id), static, where)
                continue
            parent, child = (
                str(tr.header.frame_id).lstrip("/"),
                str(tr.child_frame_id).lstrip("/"),
            )
            edge = f"{parent}->{child}"
            euler_from_quaternion(
                q.x, q.y, q.z, q.w, f"{where} ({edge})", self.stats
            )  # the norm check
            t = stamp_us(tr.header) if self.ic.time_source == "header" else m.log_ns // 1000
            self.tree.add(
                str(tr.header.frame_id),
                str(tr.child_frame_id),
                t,
                (tl.x, tl.y, tl.z),
                (q.x, q.y, q.z, q.w),
                static,
                where,
            )

    def pose(self, m: Any, where: str) -> None:
        """A pose message: its rows (time, x, y, z, roll, pitch, yaw) with the message number."""
        num = self.read[m.topic]
        if not self.pose_frame:
            self.pose_frame = {
                "pose_frame": str(m.msg.header.frame_id).lstrip("/"),
                "pose_of": str(getattr(m.msg, "child_frame_id", "") or m.topic).lstrip("/"),
            }
        self.rows.extend(
            (*r, num)
            for r in pose_rows(
                m.msg, m.msgtype, m.log_ns // 1000, self.ic.time_source, None, where, self.stats
            )
        )


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
    mode, image_topic, pose_topics = _choose(sc, topics, src, fmt, report)
    store = tmp / "images" / sc.camera
    store.mkdir(parents=True)
    r = _LogReading(ic, store, sc.camera, report["dropped"])
    try:
        for m in stream(readable, fmt, (image_topic, *pose_topics), salvage=ic.salvage):
            r.read[m.topic] += 1
            where = f"{src}: {m.topic} message {r.read[m.topic]}"
            if m.topic == image_topic:
                r.image(m, where)
            elif mode == "tf":
                r.transforms(m, where)
            else:
                r.pose(m, where)
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
    report["messages_read"] = dict(sorted(r.read.items()))
    if sum(r.read.values()) == 0:
        raise IngestError(
            f"{src}: the log has no message on {image_topic} or {', '.join(pose_topics)} "
            "(empty log)"
        )
    if not r.img_t:
        raise IngestError(f"{src}: no image message on {image_topic}")
    report["normalised"] = {"quaternion_normalised": r.stats.get("quaternion_normalised", 0)}
    img_arr, size_arr = np.array(r.img_t, np.int64), np.array(r.sizes, np.int64)
    if mode == "tf":
        return _finish_tf(sc, ic, tmp, r, report, src)
    if mode == "none":  # no trajectory: every image is a frame, its pose unknown (NaN)
        poses = np.full((len(img_arr), 6), np.nan)
        return write_frames(
            sc, tmp, img_arr, r.uris, size_arr, poses, np.ones(len(img_arr), bool), report
        )
    if not r.rows:
        raise IngestError(f"{src}: no pose message on {pose_topics[0]}")
    report["pose_frames"] = r.pose_frame
    pose_arr = np.array(r.rows, dtype=np.float64)
    pose_t = pose_arr[:, 0].astype(np.int64)
    check_monotonic(
        pose_t, f"{src}: {pose_topics[0]}", "pose", numbers=pose_arr[:, 7].astype(np.int64)
    )
    return finish(sc, ic, tmp, (img_arr, r.uris, size_arr), (pose_t, pose_arr[:, 1:7]), report)


def _tf_ends(
    sc: SessionConfig, tree: TfTree, frame_ids: Counter[str], src: Path
) -> tuple[str, str, list[str]]:
    """(fixed frame, camera frame, roots) of the tf tree: from the config or the only choice.

    Raises:
        IngestError: no transform, a loop, several roots and no fixed_frame, several image frames
            and no camera_frame, or a named frame not in the tree.
    """
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
    return fixed, camera, roots


def _finish_tf(
    sc: SessionConfig,
    ic: IngestConfig,
    tmp: Path,
    r: _LogReading,
    report: dict,
    src: Path,
) -> pd.DataFrame:
    """Camera poses composed through the tf tree at the image times (method §3).

    ``r``: what the pass over the log gathered (images, the tf tree, the images' frame ids).
    """
    tree = r.tree
    img_t, sizes = np.array(r.img_t, np.int64), np.array(r.sizes, np.int64)
    fixed, camera, roots = _tf_ends(sc, tree, r.frame_ids, src)
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
    return write_frames(sc, tmp, img_t, r.uris, sizes, poses, ok, report)

"""``harness inspect LOG``: what a user runs first on an unknown log.

Topics with types, counts, rates and time spans; image encodings, sizes and frame ids; the tf tree
(parent, child, static or dynamic, rate); and the config lines that would ingest the log. One
pass over the log: message payloads are not deserialized except the first image of each image
topic and the (small) transform messages.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import IngestError
from harness.ingest.folder_inspect import time_span
from harness.ingest.images import compressed_size
from harness.ingest.log_types import IMAGE_TYPES, READ_ERRORS, typestore_for, uri_safe_path
from harness.ingest.logs import READERS, detect_format, list_topics
from harness.ingest.poses import POSE_TYPES, stamp_us
from harness.ingest.tf import TfTree

TF_TYPE = "tf2_msgs/msg/TFMessage"


def inspect_log(path: Path) -> dict[str, Any]:
    """Describe a log (NCLT root, ROS1 bag, ROS2 bag directory or MCAP) as a dict.

    Raises:
        IngestError: The path is no log of a known format, or cannot be read.
    """
    path = Path(path)
    fmt = detect_format(path)
    inspect = READERS[fmt].inspect
    if inspect is not None:  # a layout of its own (nclt, a folder): its record says
        return inspect(path)
    from rosbags.highlevel import AnyReader

    with uri_safe_path(path) as readable:
        topics = list_topics(readable, fmt)
        times: dict[str, list[int]] = {t: [] for t in topics}
        images: dict[str, dict[str, Any]] = {}
        tree = TfTree()
        tf_counts: dict[str, list[int]] = {}
        try:
            with AnyReader([readable], default_typestore=typestore_for(fmt)) as reader:
                for conn, t, raw in reader.messages():
                    times.setdefault(conn.topic, []).append(int(t))
                    if conn.msgtype in IMAGE_TYPES and conn.topic not in images:
                        msg: Any = reader.deserialize(raw, conn.msgtype)
                        images[conn.topic] = _image_info(msg, conn.msgtype)
                    elif conn.msgtype == TF_TYPE:
                        msg = reader.deserialize(raw, conn.msgtype)
                        static = conn.topic.rstrip("/").endswith("tf_static")
                        for tr in msg.transforms:
                            tl, q = tr.transform.translation, tr.transform.rotation
                            tree.add(
                                tr.header.frame_id,
                                tr.child_frame_id,
                                stamp_us(tr.header),
                                (tl.x, tl.y, tl.z),
                                (q.x, q.y, q.z, q.w),
                                static,
                                f"{path}: {conn.topic}",
                            )
                            tf_counts.setdefault(
                                f"{tr.header.frame_id.lstrip('/')}->{tr.child_frame_id.lstrip('/')}",
                                [],
                            ).append(stamp_us(tr.header) * 1000)
        except READ_ERRORS as err:  # a reader failure is damage; the tf tree's own errors pass
            raise IngestError(
                f"{path}: cannot read the whole log ({type(err).__name__}: {err}); try "
                "`harness ingest --salvage`"
            ) from None
    out: dict[str, Any] = {
        "path": str(path),
        "format": fmt,
        "topics": [],
        "images": images,
        "tf": [],
        "suggested_config": "",
    }
    for name, (typ, count) in sorted(topics.items()):
        out["topics"].append(
            {"topic": name, "type": typ, "messages": count, **time_span(times.get(name, []))}
        )
    for e in sorted(tree.edges.values(), key=lambda e: (e.parent, e.child)):
        sp = time_span(tf_counts.get(e.name, []))
        out["tf"].append(
            {
                "parent": e.parent,
                "child": e.child,
                "static": e.static,
                "transforms": len(e.times),
                "rate_hz": sp["rate_hz"],
            }
        )
    out["tf_roots"] = tree.roots()
    out["suggested_config"] = _suggest(path, topics, images, tree)
    return out


def _image_info(msg: Any, msgtype: str) -> dict[str, Any]:
    info: dict[str, Any] = {"frame_id": str(msg.header.frame_id)}
    if msgtype.endswith("CompressedImage"):
        data = bytes(np.asarray(msg.data, dtype=np.uint8))
        w: int | None
        h: int | None
        try:
            w, h = compressed_size(data, "image")
        except IngestError:
            w = h = None
        info.update({"encoding": f"compressed: {msg.format}", "width": w, "height": h})
    else:
        info.update(
            {"encoding": str(msg.encoding), "width": int(msg.width), "height": int(msg.height)}
        )
    return info


def _suggest(
    path: Path, topics: dict[str, tuple[str, int]], images: dict[str, dict[str, Any]], tree: Any
) -> str:
    lines = [
        "[[sessions]]",
        f'name = "{path.stem}"',
        'season = ""  # WI, SP, SU or AU',
        f'source = "{path}"',
    ]
    img = sorted(t for t, (typ, _) in topics.items() if typ in IMAGE_TYPES)
    poses = sorted(t for t, (typ, _) in topics.items() if typ in POSE_TYPES and typ != TF_TYPE)
    if img:
        lines.append(
            f'image_topic = "{img[0]}"'
            + (f"  # also: {', '.join(img[1:])}" if len(img) > 1 else "")
        )
    if poses:
        lines.append(
            f'pose_topic = "{poses[0]}"'
            + (f"  # also: {', '.join(poses[1:])}" if len(poses) > 1 else "")
        )
    elif tree.edges:
        roots = tree.roots()
        cam = images.get(img[0], {}).get("frame_id", "") if img else ""
        lines.append(
            f'fixed_frame = "{roots[0] if roots else "map"}"'
            + ("  # roots: " + ", ".join(roots) if len(roots) > 1 else "")
        )
        if cam and cam.lstrip("/") in tree.frames():
            lines.append(f'camera_frame = "{cam.lstrip("/")}"  # the images\' header.frame_id')
        else:
            lines.append(
                f'camera_frame = "..."  # the images\' frame {cam!r} is not in the tree; '
                f"frames: {', '.join(sorted(tree.frames()))}"
            )
    return "\n".join(lines)

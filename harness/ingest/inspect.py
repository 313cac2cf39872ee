"""``harness inspect LOG``: what a user runs first on an unknown log.

Topics with types, counts, rates and time spans; image encodings, sizes and frame ids; the tf tree
(parent, child, static or dynamic, rate); and the config lines that would ingest the log. One
pass over the log: message payloads are not deserialized except the first image of each image
topic and the (small) transform messages.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import IngestError
from harness.imagestore import header_size
from harness.ingest.folders import FOLDER_FORMATS, INTEGER_UNITS
from harness.ingest.images import compressed_size
from harness.ingest.log_types import IMAGE_TYPES, READ_ERRORS, typestore_for, uri_safe_path
from harness.ingest.logs import READERS, detect_format, list_topics
from harness.ingest.poses import POSE_TYPES, stamp_us
from harness.ingest.tf import TfTree

TF_TYPE = "tf2_msgs/msg/TFMessage"


def _span(times: list[int]) -> dict[str, Any]:
    if not times:
        return {"first_s": None, "last_s": None, "span_s": 0.0, "rate_hz": 0.0}
    t = np.asarray(times, np.int64)
    span = float(t.max() - t.min()) / 1e9
    return {
        "first_s": float(t.min()) / 1e9,
        "last_s": float(t.max()) / 1e9,
        "span_s": round(span, 3),
        "rate_hz": round((len(t) - 1) / span, 3) if span > 0 else 0.0,
    }


def inspect_log(path: Path) -> dict[str, Any]:
    """Describe a log (NCLT root, ROS1 bag, ROS2 bag directory or MCAP) as a dict.

    Raises:
        IngestError: The path is no log of a known format, or cannot be read.
    """
    path = Path(path)
    fmt = detect_format(path)
    inspect = READERS[fmt].inspect
    if inspect is not None:  # a layout of its own (nclt)
        return inspect(path)
    if fmt in FOLDER_FORMATS:
        return inspect_folder(path, fmt)
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
            {"topic": name, "type": typ, "messages": count, **_span(times.get(name, []))}
        )
    for e in sorted(tree.edges.values(), key=lambda e: (e.parent, e.child)):
        sp = _span(tf_counts.get(e.name, []))
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


#: How :func:`harness.ingest.folders.stem_to_ns` reads an integer file name, by its factor to ns.
_UNIT_WORDS = {1: "ns", 1_000: "us", 1_000_000: "ms", 1_000_000_000: "s"}


def _name_pattern(stems: list[str]) -> str:
    """How a folder's file names are read as times (SPEC 13.2's folders)."""
    if not stems:
        return "no images"
    if all(s.isdigit() for s in stems):
        units = {_UNIT_WORDS[next(f for lo, f in INTEGER_UNITS if int(s) >= lo)] for s in stems}
        return "integers, times in " + " and ".join(sorted(units))
    try:
        [float(s) for s in stems]
    except ValueError:
        return "names (not times): frames one second apart in name order"
    return "decimal numbers, times in seconds"


def inspect_folder(path: Path, fmt: str) -> dict[str, Any]:
    """Describe a folder session (images alone, or TUM, KITTI, EuRoC) as a dict.

    The images' count, sizes (from their headers, never decoding pixels), how their names read
    as times, whether those times increase in name order, the span and rate, the trajectory's
    poses, and the config lines that would ingest it.

    Raises:
        IngestError: the folder's times or trajectory cannot be read (one line naming the file).
    """
    reader = FOLDER_FORMATS[fmt]
    try:
        frames = reader.images(path)
        poses = reader.poses(path)
    except ValueError as err:
        raise IngestError(str(err)) from None
    sizes: dict[str, int] = {}
    for _, f in frames:
        w, h = header_size(f, str(f))
        sizes[f"{w}x{h}"] = sizes.get(f"{w}x{h}", 0) + 1
    stems = [f.stem for _, f in frames]
    times = [t for t, _ in frames]
    info: dict[str, Any] = {
        "path": str(path),
        "format": fmt,
        "images": len(frames),
        "sizes": sizes,
        "first": frames[0][1].name if frames else None,
        "last": frames[-1][1].name if frames else None,
        "names": _name_pattern(stems),
        "times_file": (path / "times.txt").exists() if fmt == "images" else None,
        "in_order": all(b > a for a, b in itertools.pairwise(times)),
        "poses": len(poses),
        **_span(times),
    }
    lines = ["[[sessions]]", f'name = "{path.name}"', 'season = ""', f'source = "{path}"']
    if fmt == "images":
        lines.append("# no trajectory: pair it with another folder by retrieval ([pairs] by)")
    info["suggested_config"] = "\n".join(lines)
    return info

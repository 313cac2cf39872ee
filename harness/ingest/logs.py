"""Streaming message access to ROS1 bags, ROS2 bags (sqlite3 or mcap storage) and plain MCAP files.

Messages are read one at a time through rosbags' ``AnyReader``; memory stays bounded whatever
the log's size. A truncated MCAP whose summary is missing is read record by record with the
mcap library's stream reader, so the messages before the damage can still be kept.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

from harness.errors import IngestError, TopicError
from harness.ingest.folder_inspect import inspect_folder
from harness.ingest.folders import FOLDER_FORMATS
from harness.ingest.log_types import (
    IMAGE_TYPES,
    LogFormat,
    LogReader,
    Message,
)
from harness.ingest.nclt_session import check_nclt_camera, ingest_nclt, inspect_nclt, nclt_sources
from harness.ingest.poses import POSE_TYPES
from harness.ingest.rosbags_log import RosbagsLog
from harness.methods import Registry

#: Every log format by name (a session's ``format``): the built-in ones, then registered ones.
READERS: Registry[LogFormat] = Registry("log format")


def register_format(name: str, reader: LogReader) -> None:
    """Add a log format, named by a session's ``format`` or found by ``reader.detect``.

    Registered readers are asked before the built-in layouts are looked for.

    Raises:
        ValueError: ``name`` is taken.
    """
    READERS.add(name, LogFormat(name, reader))


def known_formats() -> tuple[str, ...]:
    """Every log format a session may name: the built-in ones, then registered ones."""
    return tuple(READERS)


def detect_format(path: Path) -> str:
    """The format of what is at ``path``: a registered one's, else a built-in layout's.

    Raises:
        IngestError: The path does not exist or is of no known format.
    """
    path = Path(path)
    if not path.exists():
        raise IngestError(f"{path}: no such file or directory")
    asked = sorted(READERS.values(), key=lambda f: (f.builtin, f.detect_order))
    found = [f.name for f in asked if f.reader.detect(path)]
    if found:
        return found[0]
    if path.is_dir():
        raise IngestError(
            f"{path}: directory is neither a ROS2 bag (no metadata.yaml), an NCLT root "
            "(no images/ or ground_truth/) nor a folder of images with a TUM, KITTI or EuRoC "
            "trajectory (groundtruth.txt + rgb/, times.txt + poses.txt, "
            "mav0/state_groundtruth_estimate0/data.csv)"
        )
    if path.suffix == ".db3":
        raise IngestError(
            f"{path}: a bare .db3 file; pass the ROS2 bag directory that holds it and metadata.yaml"
        )
    raise IngestError(
        f"{path}: unknown log format (expected an NCLT root, a .bag, a ROS2 bag directory "
        "or an .mcap)"
    )


def _format(fmt: str) -> LogFormat:
    if fmt not in READERS or not READERS[fmt].streams:
        raise IngestError(f"no message stream for log format {fmt!r}; known: {known_formats()}")
    return READERS[fmt]


def list_topics(path: Path, fmt: str, salvage: bool = False) -> dict[str, tuple[str, int]]:
    """Topic -> (message type, message count) of a log of format ``fmt``.

    A log that cannot be opened is read sequentially where that is possible (MCAP always, ROS1
    and ROS2 bags with ``salvage``); a damaged log whose topics cannot be read is a
    :class:`CorruptLogError`, never an "empty" log.
    """
    f = _format(fmt)
    if f.builtin:
        return dict(f.reader.topics(Path(path), salvage=salvage))
    return dict(f.reader.topics(Path(path)))


def choose_topics(
    topics: dict[str, tuple[str, int]], image_topic: str | None, pose_topic: str | None, where: str
) -> tuple[str, str]:
    """Pick the image and the pose topic: given ones are checked, else the only candidate is taken.

    Raises:
        TopicError: A named topic is missing or of the wrong type, or none or several candidates
            exist.
    """

    def pick(name: str | None, types: tuple[str, ...], what: str, flag: str) -> str:
        cands = sorted(t for t, (typ, _) in topics.items() if typ in types)
        listing = ", ".join(f"{t} ({topics[t][0]})" for t in sorted(topics)) or "none"
        if name is not None:
            if name not in topics:
                raise TopicError(
                    f"{where}: {what} topic {name!r} is not in the log; topics: {listing}"
                )
            if topics[name][0] not in types:
                raise TopicError(
                    f"{where}: topic {name!r} has type {topics[name][0]}, not an {what} "
                    f"type {list(types)}"
                )
            return name
        if not cands:
            raise TopicError(f"{where}: no {what} topic (types {list(types)}); topics: {listing}")
        if len(cands) > 1:
            raise TopicError(f"{where}: several {what} topics {cands}; choose one with {flag}")
        return cands[0]

    if not topics:
        raise IngestError(f"{where}: the log is empty (no topics)")
    return (
        pick(image_topic, IMAGE_TYPES, "image", "--image-topic"),
        pick(pose_topic, POSE_TYPES, "pose", "--pose-topic"),
    )


def _folder_call(path: Path, fmt: str, fn: Any) -> Any:
    """A folder reader's result; its ``ValueError`` or ``OSError`` as one :class:`IngestError`."""
    try:
        return fn()
    except (ValueError, OSError) as err:
        raise IngestError(f"{path} ({fmt} folder): {err}") from None


def stream(
    path: Path, fmt: str, topics: tuple[str, ...], salvage: bool = False
) -> Iterator[Message]:
    """Yield the messages of ``topics`` in log order, deserialized, from a log of format ``fmt``.

    Raises:
        CorruptLogError: The log is damaged; ``messages_read`` says how many were yielded before.
    """
    f = _format(fmt)
    if f.builtin:
        yield from f.reader.messages(Path(path), topics, salvage=salvage)
    else:
        yield from f.reader.messages(Path(path), topics)


class FolderLog:
    """A folder of images with a TUM, KITTI or EuRoC trajectory (:mod:`harness.ingest.folders`)."""

    def __init__(self, folder: Any) -> None:
        self.folder = folder

    def detect(self, path: Path) -> bool:
        """Whether ``path`` is a folder of this layout."""
        return bool(self.folder.detect(path))

    def topics(self, path: Path, salvage: bool = False) -> dict[str, tuple[str, int]]:
        """The image and the pose topic with their counts."""
        return dict(_folder_call(path, self.folder.name, lambda: self.folder.topics(Path(path))))

    def messages(
        self, path: Path, topics: tuple[str, ...], salvage: bool = False
    ) -> Iterator[Message]:
        """The poses and images in time order, one image in memory at a time."""
        recs = self.folder.raw(Path(path), topics)
        while True:
            try:
                topic, typ, t, msg = next(recs)
            except StopIteration:
                break
            except (ValueError, OSError) as err:
                raise IngestError(f"{path} ({self.folder.name} folder): {err}") from None
            yield Message(topic, typ, t, msg)


class NcltLayout:
    """An NCLT session root (``images/`` or ``ground_truth/``), read by ``nclt_session``."""

    def detect(self, path: Path) -> bool:
        """A directory holding ``images/`` or ``ground_truth/``."""
        return path.is_dir() and ((path / "images").is_dir() or (path / "ground_truth").is_dir())


def _register_builtins() -> None:
    """The built-in formats, in the order sessions list them; detection asks folders first."""
    order = {"tum": 0, "kitti": 0, "euroc": 0, "ros2": 1, "nclt": 2, "ros1": 3, "mcap": 4}
    nclt = LogFormat(
        "nclt",
        NcltLayout(),
        True,
        order["nclt"],
        streams=False,
        ingest=ingest_nclt,
        sources=nclt_sources,
        check=check_nclt_camera,
        inspect=inspect_nclt,
    )
    READERS.add("nclt", nclt)
    for fmt in ("ros1", "ros2", "mcap"):
        READERS.add(fmt, LogFormat(fmt, RosbagsLog(fmt), True, order[fmt]))
    for name, folder in FOLDER_FORMATS.items():
        look = partial(inspect_folder, fmt=name)
        READERS.add(
            name, LogFormat(name, FolderLog(folder), True, order.get(name, 0), inspect=look)
        )


_register_builtins()

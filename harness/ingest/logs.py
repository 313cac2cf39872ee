"""Streaming message access to ROS1 bags, ROS2 bags (sqlite3 or mcap storage) and plain MCAP files.

Messages are read one at a time through rosbags' ``AnyReader``; memory stays bounded whatever
the log's size. A truncated MCAP whose summary is missing is read record by record with the
mcap library's stream reader, so the messages before the damage can still be kept.
"""

from __future__ import annotations

import contextlib
import sqlite3
import struct
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from harness.errors import CorruptLogError, IngestError, TopicError
from harness.ingest import salvage as salvage_mod
from harness.ingest.folders import FOLDER_FORMATS
from harness.ingest.poses import POSE_TYPES
from harness.methods import Registry

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
#: What a log reader raises on a damaged or truncated file (reported as damage, never a traceback).
READ_ERRORS: tuple[type[BaseException], ...] = (
    AnyReaderError,
    struct.error,
    sqlite3.DatabaseError,
    EOFError,
    ValueError,
    KeyError,
    IndexError,
    OSError,
)
try:  # a payload that does not deserialize (a row cut short, zeros past the end of a file)
    from rosbags.serde.errors import SerdeError

    READ_ERRORS = (*READ_ERRORS, SerdeError)
except ImportError:  # pragma: no cover
    pass
try:  # reader errors of the subpackages
    from rosbags.rosbag1 import ReaderError as _R1
    from rosbags.rosbag2 import ReaderError as _R2

    READ_ERRORS = (*READ_ERRORS, _R1, _R2)
except ImportError:  # pragma: no cover
    pass
try:  # a corrupt zstd-compressed MCAP chunk
    from zstandard import ZstdError

    READ_ERRORS = (*READ_ERRORS, ZstdError)
except ImportError:  # pragma: no cover
    pass
try:
    from backports.zstd import ZstdError as _BZ

    READ_ERRORS = (*READ_ERRORS, _BZ)
except ImportError:  # pragma: no cover
    pass
try:
    from mcap.exceptions import McapError

    READ_ERRORS = (*READ_ERRORS, McapError)
except ImportError:  # pragma: no cover
    pass


@contextlib.contextmanager
def uri_safe_path(path: Path) -> Iterator[Path]:
    """``path``, or a symbolic link to it in a temporary directory.

    The link is made when the name holds a character that breaks the ``file:`` URIs rosbags opens
    sqlite3 databases with (``#``, ``?``, ``%``).
    """
    if not any(c in str(Path(path).resolve()) for c in "#?%"):
        yield Path(path)
        return
    with tempfile.TemporaryDirectory(prefix="dbl-harness-log-") as d:
        link = Path(d) / ("log" + Path(path).suffix)  # readers choose by suffix
        src = Path(path).resolve()
        if src.is_dir():  # a real directory of links: readers resolve the directory's own path
            link.mkdir()
            for child in src.iterdir():
                (link / child.name).symlink_to(child)
        else:
            link.symlink_to(src)
        yield link


class LogReader(Protocol):
    """A log format beside the built-in ones (:func:`register_format`).

    Messages are rosbags-style objects (a ``sensor_msgs``/``nav_msgs``/``geometry_msgs``/
    ``tf2_msgs`` message of the ROS2 typestore, e.g. from ``typestore.deserialize_cdr``);
    everything after the stream (images, poses, tf, drops, the report) is shared.
    """

    def detect(self, path: Path) -> bool:
        """Whether ``path`` is a log of this format."""
        ...

    def topics(self, path: Path) -> dict[str, tuple[str, int]]:
        """Topic -> (message type, message count)."""
        ...

    def messages(self, path: Path, topics: tuple[str, ...]) -> Iterator[Message]:
        """The messages of ``topics`` in log order (log time in ns)."""
        ...


@dataclass(frozen=True)
class LogFormat:
    """One log format of the registry: its reader and how it is asked.

    The built-in formats are records like a user's (:func:`register_format`); their readers also
    take ``salvage`` (read what a damaged log still holds), and ``nclt`` is a session layout read
    by :mod:`harness.ingest.nclt_session` rather than a stream of messages.
    """

    name: str
    reader: Any  # a LogReader; a built-in one's topics and messages also take ``salvage``
    builtin: bool = False
    #: Order in which built-in formats are asked whether a path is theirs (registered ones first).
    detect_order: int = 0
    #: False for a session layout of its own (``nclt``): no topics, no message stream.
    streams: bool = True


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


@dataclass(frozen=True)
class Message:
    """One log message: topic, type, log time (ns) and the deserialized message."""

    topic: str
    msgtype: str
    log_ns: int
    msg: Any  # a deserialized rosbags message: its type is built at run time


def typestore_for(fmt: str):
    """The rosbags type store a log of format ``fmt`` falls back on (ROS1 Noetic, ROS2 Humble)."""
    return get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)


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


def _salvage_stream(path: Path, fmt: str, topics: tuple[str, ...]) -> Iterator[Message]:
    """Sequential read of a ROS1 or ROS2 bag that rosbags cannot open (see :mod:`.salvage`)."""
    if fmt == "ros2" and sorted(Path(path).glob("*.mcap")):
        yield from _mcap_stream(sorted(Path(path).glob("*.mcap"))[0], topics)
        return
    raw = (
        salvage_mod.ros1_messages(path, topics)
        if fmt == "ros1"
        else salvage_mod.ros2_sqlite_messages(path, topics)
    )
    de = salvage_mod.deserializer(fmt)
    n = undecodable = 0
    first = ""
    try:
        for topic, typ, t, data in raw:
            try:
                msg = de(data, typ)
            except READ_ERRORS as err:
                if fmt == "ros1":  # a sequential read: nothing after a bad record is trusted
                    raise CorruptLogError(
                        path, n, f"message {n + 1} does not deserialize: {err}", salvage=True
                    ) from None
                undecodable += 1  # a sqlite row holding zeros: its neighbours are still good
                first = first or f"message {n + undecodable} does not deserialize: {err}"
                continue
            n += 1
            yield Message(topic, typ, t, msg)
    except CorruptLogError as err:
        if not undecodable:
            raise
        raise CorruptLogError(
            path,
            n,
            f"{err.detail}; {undecodable} undecodable message(s) skipped ({first})",
            salvage=True,
        ) from None
    if undecodable:
        raise CorruptLogError(
            path, n, f"{undecodable} undecodable message(s) skipped ({first})", salvage=True
        )


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


class RosbagsLog:
    """ROS1 bags, ROS2 bags (sqlite3 or mcap storage) and plain MCAP files, through rosbags.

    Read with ``AnyReader``; one that cannot be opened is read sequentially where that is possible
    (MCAP always, ROS1 and ROS2 bags with ``salvage``).
    """

    def __init__(self, fmt: str) -> None:
        self.fmt = fmt

    def detect(self, path: Path) -> bool:
        """A ``.bag`` file (ros1), a directory with ``metadata.yaml`` (ros2), an ``.mcap`` file."""
        if self.fmt == "ros2":
            return path.is_dir() and (path / "metadata.yaml").exists()
        return not path.is_dir() and path.suffix == (".bag" if self.fmt == "ros1" else ".mcap")

    def topics(self, path: Path, salvage: bool = False) -> dict[str, tuple[str, int]]:
        """Topic -> (message type, message count); see :func:`list_topics`."""
        fmt = self.fmt
        try:
            with AnyReader([Path(path)], default_typestore=typestore_for(fmt)) as reader:
                return {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        except READ_ERRORS as err:
            found: dict[str, tuple[str, int]] = {}
            if fmt == "mcap":
                found = _mcap_stream_topics(Path(path))
            elif salvage and fmt == "ros1":
                found = salvage_mod.ros1_topics(Path(path))
            elif salvage and fmt == "ros2":
                mc = sorted(Path(path).glob("*.mcap"))
                found = (
                    _mcap_stream_topics(mc[0]) if mc else salvage_mod.ros2_sqlite_topics(Path(path))
                )
            if not found:
                raise CorruptLogError(path, 0, f"cannot open: {err}", salvage=salvage) from None
            return found

    def messages(
        self, path: Path, topics: tuple[str, ...], salvage: bool = False
    ) -> Iterator[Message]:
        """The messages of ``topics`` in log order; see :func:`stream`."""
        fmt = self.fmt
        n = 0
        try:
            reader = AnyReader([Path(path)], default_typestore=typestore_for(fmt))
            reader.open()
        except READ_ERRORS as err:
            if fmt == "mcap":
                yield from _mcap_stream(Path(path), topics, salvage)
                return
            if salvage:
                yield from _salvage_stream(Path(path), fmt, topics)
                return
            raise CorruptLogError(path, 0, f"cannot open: {err}") from None
        try:
            conns = [c for c in reader.connections if c.topic in topics]
            it = reader.messages(connections=conns)
            while True:
                try:
                    conn, t, raw = next(it)
                    msg = reader.deserialize(raw, conn.msgtype)
                except StopIteration:
                    break
                except READ_ERRORS as err:
                    raise CorruptLogError(
                        path, n, f"{type(err).__name__}: {err}", salvage=salvage
                    ) from None
                n += 1
                yield Message(conn.topic, conn.msgtype, int(t), msg)
        finally:
            with contextlib.suppress(*READ_ERRORS):  # closing a damaged file may fail again
                reader.close()


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


def _mcap_records(path: Path) -> Iterator[object]:
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as fh:
        yield from StreamReader(fh, skip_magic=False).records


def _mcap_stream_topics(path: Path) -> dict[str, tuple[str, int]]:
    from mcap.records import Channel, Schema
    from mcap.records import Message as McapMessage

    schemas: dict[int, str] = {}
    chans: dict[int, tuple[str, str]] = {}
    counts: dict[str, int] = {}
    try:
        for rec in _mcap_records(path):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec.name
            elif isinstance(rec, Channel):
                chans[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
            elif isinstance(rec, McapMessage) and rec.channel_id in chans:
                counts[chans[rec.channel_id][0]] = counts.get(chans[rec.channel_id][0], 0) + 1
    except READ_ERRORS:
        pass
    return {t: (typ, counts.get(t, 0)) for t, typ in chans.values()}


def _mcap_stream(path: Path, topics: tuple[str, ...], salvage: bool = False) -> Iterator[Message]:
    """Sequential record-by-record read of an MCAP file whose index or summary is unusable."""
    from mcap.records import Channel, Schema
    from mcap.records import Message as McapMessage

    store = get_typestore(Stores.EMPTY)
    schemas: dict[int, Schema] = {}
    chans: dict[int, tuple[str, str]] = {}
    n = 0
    try:
        for rec in _mcap_records(path):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
                if rec.encoding == "ros2msg" and rec.name not in store.fielddefs:
                    store.register(get_types_from_msg(rec.data.decode(), rec.name))
            elif isinstance(rec, Channel):
                chans[rec.id] = (
                    rec.topic,
                    schemas[rec.schema_id].name if rec.schema_id in schemas else "",
                )
            elif isinstance(rec, McapMessage):
                topic, typ = chans.get(rec.channel_id, ("", ""))
                if topic in topics:
                    msg = store.deserialize_cdr(rec.data, typ)
                    n += 1
                    yield Message(topic, typ, int(rec.log_time), msg)
    except READ_ERRORS as err:
        raise CorruptLogError(path, n, f"{type(err).__name__}: {err}", salvage=salvage) from None
    if n == 0:
        raise CorruptLogError(path, 0, "no readable message", salvage=salvage)


def _register_builtins() -> None:
    """The built-in formats, in the order sessions list them; detection asks folders first."""
    order = {"tum": 0, "kitti": 0, "euroc": 0, "ros2": 1, "nclt": 2, "ros1": 3, "mcap": 4}
    READERS.add("nclt", LogFormat("nclt", NcltLayout(), True, order["nclt"], streams=False))
    for fmt in ("ros1", "ros2", "mcap"):
        READERS.add(fmt, LogFormat(fmt, RosbagsLog(fmt), True, order[fmt]))
    for name, folder in FOLDER_FORMATS.items():
        READERS.add(name, LogFormat(name, FolderLog(folder), True, order.get(name, 0)))


_register_builtins()

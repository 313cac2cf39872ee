"""What every log reader shares: the message, the reader and format records, the read errors."""

from __future__ import annotations

import contextlib
import sqlite3
import struct
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from rosbags.highlevel import AnyReaderError
from rosbags.typesys import Stores, get_typestore


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
    #: A layout's own ingest, (session, [ingest], entry dir, report) -> frames; None: the messages
    #: are streamed through :func:`harness.ingest.log_session.ingest_log`.
    ingest: Callable[..., Any] | None = None
    #: The files a session of this layout reads, by name (its cache key's); None: its source.
    sources: Callable[..., dict[str, Path]] | None = None
    #: Checks a session of this layout before any work (its camera, say); None: none.
    check: Callable[..., None] | None = None
    #: What ``harness inspect`` says of a path of this layout; None: its topics and messages.
    inspect: Callable[[Path], dict[str, Any]] | None = None


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

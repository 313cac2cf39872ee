"""ROS1 bags, ROS2 bags and plain MCAP files read through rosbags, message by message.

A truncated MCAP whose summary is missing is read record by record with the mcap library's
stream reader, so the messages before the damage can still be kept.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from harness.errors import CorruptLogError
from harness.ingest import salvage as salvage_mod
from harness.ingest.log_types import (
    READ_ERRORS,
    Message,
    typestore_for,
)


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

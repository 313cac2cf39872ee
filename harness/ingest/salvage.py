"""Sequential readers for damaged logs (``--salvage``): keep every message before the damage.

rosbags' readers need a ROS1 bag's index (written at the end, so a truncated bag has none) and a
ROS2 bag's intact database. These readers walk the file from its start instead:

- ROS1: record by record (bag header, connections, chunks with ``none``, ``bz2`` or ``lz4``
  compression, messages), stopping at the first damaged record or chunk;
- ROS2 sqlite3: the ``messages`` table in insertion order; past the damage sqlite reports, row by
  row by id (rows on intact pages are kept, unreadable ones skipped and counted); ROS2 with MCAP
  storage: the MCAP stream reader.
"""

from __future__ import annotations

import bz2
import sqlite3
import struct
from collections.abc import Iterator
from pathlib import Path

from rosbags.typesys import Stores, get_typestore

from harness.errors import CorruptLogError, IngestError

ROS1_MAGIC = b"#ROSBAG V2.0\n"
OP_MSG, OP_CONN, OP_CHUNK = 0x02, 0x07, 0x05


class _Damaged(Exception):
    pass


def _fields(buf: bytes) -> dict[str, bytes]:
    out, i = {}, 0
    while i < len(buf):
        if i + 4 > len(buf):
            raise _Damaged("header field length cut short")
        (n,) = struct.unpack_from("<I", buf, i)
        i += 4
        if i + n > len(buf):
            raise _Damaged("header field cut short")
        name, sep, value = buf[i : i + n].partition(b"=")
        if not sep:
            raise _Damaged("header field without '='")
        out[name.decode(errors="replace")] = value
        i += n
    return out


def _records(buf: bytes, start: int) -> Iterator[tuple[dict[str, bytes], bytes]]:
    i = start
    while i < len(buf):
        if i + 4 > len(buf):
            raise _Damaged("record header length cut short")
        (hl,) = struct.unpack_from("<I", buf, i)
        if i + 4 + hl + 4 > len(buf):
            raise _Damaged("record header cut short")
        header = _fields(buf[i + 4 : i + 4 + hl])
        (dl,) = struct.unpack_from("<I", buf, i + 4 + hl)
        d0 = i + 8 + hl
        if d0 + dl > len(buf):
            raise _Damaged("record data cut short")
        yield header, buf[d0 : d0 + dl]
        i = d0 + dl


def _decompress(kind: str, data: bytes, size: int) -> bytes:
    if kind == "none":
        return data
    try:
        if kind == "bz2":
            out = bz2.decompress(data)
        elif kind == "lz4":
            import lz4.frame

            out = lz4.frame.decompress(data)
        else:
            raise _Damaged(f"unknown chunk compression {kind!r}")
    except (OSError, ValueError, RuntimeError, EOFError) as err:
        raise _Damaged(f"chunk does not decompress: {err}") from None
    if len(out) != size:
        raise _Damaged(f"chunk decompresses to {len(out)} bytes, {size} expected")
    return out


def _ros1_type(name: str) -> str:
    pkg, _, msg = name.partition("/")
    return f"{pkg}/msg/{msg}"


def ros1_messages(
    path: Path, topics: tuple[str, ...] | None
) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, ROS2-style type, log time in ns, raw ROS1 bytes) of every readable message.

    In file order.

    Raises:
        CorruptLogError: at the first damaged record, with the count of messages yielded before it.
    """
    buf = Path(path).read_bytes()
    if not buf.startswith(ROS1_MAGIC):
        raise CorruptLogError(path, 0, "not a ROS1 bag (no '#ROSBAG V2.0' magic)", salvage=True)
    conns: dict[int, tuple[str, str]] = {}
    n = 0

    def walk(data: bytes, start: int) -> Iterator[tuple[str, str, int, bytes]]:
        nonlocal n
        for header, payload in _records(data, start):
            op = header.get("op", b"\xff")[0]
            if op == OP_CHUNK:
                size = struct.unpack("<I", header["size"])[0]
                yield from walk(_decompress(header["compression"].decode(), payload, size), 0)
            elif op == OP_CONN:
                cid = struct.unpack("<I", header["conn"])[0]
                info = _fields(payload)
                conns[cid] = (header["topic"].decode(), _ros1_type(info["type"].decode()))
            elif op == OP_MSG:
                cid = struct.unpack("<I", header["conn"])[0]
                sec, nsec = struct.unpack("<II", header["time"])
                if cid in conns and (topics is None or conns[cid][0] in topics):
                    n += 1
                    yield conns[cid][0], conns[cid][1], sec * 1_000_000_000 + nsec, payload

    try:
        yield from walk(buf, len(ROS1_MAGIC))
    except (_Damaged, KeyError, struct.error, IndexError) as err:
        raise CorruptLogError(path, n, f"{type(err).__name__}: {err}", salvage=True) from None


def ros1_topics(path: Path) -> dict[str, tuple[str, int]]:
    """Topic -> (type, readable messages) of a damaged ROS1 bag, read sequentially."""
    counts: dict[str, tuple[str, int]] = {}
    try:
        for topic, typ, _, _ in ros1_messages(path, None):
            counts[topic] = (typ, counts.get(topic, (typ, 0))[1] + 1)
    except CorruptLogError:
        pass
    return counts


def _ros2_db(path: Path) -> Path:
    dbs = sorted(Path(path).glob("*.db3"))
    if not dbs:
        raise IngestError(
            f"{path}: --salvage reads sqlite3 ROS2 bags and MCAP storage; no .db3 file found"
        )
    return dbs[0]


def _open_damaged(db: Path) -> sqlite3.Connection:
    """A read-only connection to a sqlite file that may be cut short.

    sqlite refuses a file shorter than the page count its header records ("database disk image
    is malformed" on the first query), which is what a bag cut while it was written looks like.
    ``writable_schema`` turns that check off (sqlite then takes the file's own size); the
    connection stays read-only (``mode=ro``), so nothing is written to the user's file.
    """
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    con.execute("PRAGMA writable_schema=ON")
    return con


def ros2_sqlite_messages(
    path: Path, topics: tuple[str, ...] | None
) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type, time in ns, raw CDR) of every readable row of a damaged ROS2 sqlite3 bag.

    Rows come in id (insertion) order. The table is scanned whole first, skipping rows whose cells
    read as NULL (a leaf page past the end of a cut file reads as zeros); where sqlite reports
    damage ("database disk image is malformed"), the rows after the last one read are fetched one
    by one by their id, so the rows on intact pages beyond the damage are kept too. Unreadable rows
    are skipped; when any were, a :class:`CorruptLogError` after the last row says how many (the
    ingest records it under ``salvaged``).
    """
    db = _ros2_db(path)
    n = 0
    try:
        con = _open_damaged(db)
    except sqlite3.DatabaseError as err:
        raise CorruptLogError(path, 0, f"sqlite3: {err}", salvage=True) from None
    try:
        try:
            types = {
                int(i): (str(name), str(typ))
                for i, name, typ in con.execute("SELECT id, name, type FROM topics")
            }
        except sqlite3.DatabaseError as err:
            raise CorruptLogError(path, 0, f"sqlite3 (topics table): {err}", salvage=True) from None
        last_id, error, nulls = 0, "", 0
        try:
            for rid, *cells in con.execute(
                "SELECT id, topic_id, timestamp, data FROM messages ORDER BY id"
            ):
                row = _message_row(cells)
                if row is None:  # a page read past the cut: zeros where the rows were
                    nulls += 1
                    continue
                last_id = int(rid)
                topic, typ = types.get(row[0], ("", ""))
                if topics is None or topic in topics:
                    n += 1
                    yield topic, typ, row[1], row[2]
        except sqlite3.DatabaseError as err:
            error = str(err)
        if not error and not nulls:
            return
        lost = [f"{nulls} row(s) read as zeros skipped"] if nulls else []
        if error:
            top = _max_id(con)
            skipped = pending = 0  # unreadable ids: before a later readable row, and since it
            for rid in _ids_after(con, last_id, top):
                try:
                    cells = con.execute(
                        "SELECT topic_id, timestamp, data FROM messages WHERE id = ?", (rid,)
                    ).fetchone()
                except sqlite3.DatabaseError:
                    pending += 1
                    continue
                if cells is None:
                    continue
                row = _message_row(cells)
                if row is None:
                    pending += 1
                    continue
                skipped, pending = skipped + pending, 0
                topic, typ = types.get(row[0], ("", ""))
                if topics is None or topic in topics:
                    n += 1
                    yield topic, typ, row[1], row[2]
            lost.append(f"{error}; rows read one by one past it")
            if top is not None:  # the table's last id is known: every unreadable id was a row
                lost.append(f"{skipped + pending} unreadable row(s) skipped")
            else:  # a cut file: the ids probed past the last readable row may never have existed
                lost.append(
                    f"{skipped} unreadable row(s) skipped; the table's end is cut off (no "
                    f"readable row in the {pending} ids after the last one read)"
                )
        raise CorruptLogError(path, n, "sqlite3: " + "; ".join(lost), salvage=True)
    finally:
        con.close()


def _message_row(cells) -> tuple[int, int, bytes] | None:
    """(topic id, time, data) of a messages row, or None where its cells are not those types."""
    tid, t, data = cells
    if isinstance(tid, int) and isinstance(t, int) and isinstance(data, bytes | memoryview):
        return tid, t, bytes(data)
    return None


def _max_id(con: sqlite3.Connection) -> int | None:
    """The messages table's largest id, or None where sqlite cannot read it (a cut file)."""
    try:
        top = con.execute("SELECT max(id) FROM messages").fetchone()[0]
    except sqlite3.DatabaseError:
        return None
    return None if top is None else int(top)


def _ids_after(
    con: sqlite3.Connection, last_id: int, top: int | None, misses: int = 1000
) -> Iterator[int]:
    """Message ids after ``last_id``.

    Up to ``top`` (the table's largest id) when sqlite can still say it, else until ``misses``
    ids in a row are absent or unreadable.
    """
    if top is not None:
        yield from range(last_id + 1, top + 1)
        return
    rid, gap = last_id + 1, 0
    while gap < misses:
        yield rid
        try:
            found = con.execute("SELECT 1 FROM messages WHERE id = ?", (rid,)).fetchone()
        except sqlite3.DatabaseError:
            found = None
        gap = 0 if found else gap + 1
        rid += 1


def ros2_sqlite_topics(path: Path) -> dict[str, tuple[str, int]]:
    """Topic -> (type, message count) of a ROS2 sqlite3 bag, read from its tables."""
    db = _ros2_db(path)
    try:
        con = _open_damaged(db)
        try:
            return {
                str(name): (str(typ), 0)
                for name, typ in con.execute("SELECT name, type FROM topics")
            }
        finally:
            con.close()
    except sqlite3.DatabaseError:
        return {}


def deserializer(fmt: str):
    """A function (raw bytes, type) -> message for ROS1 or CDR payloads."""
    store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    return store.deserialize_ros1 if fmt == "ros1" else store.deserialize_cdr

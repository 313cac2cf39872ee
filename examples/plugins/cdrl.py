"""A log format: JSON lines, one ``{topic, type, t_ns, cdr (base64)}`` record per message.

A plugin: then a session whose ``source`` ends in ``.cdrl`` is read by it. Run as a script it
writes one: ``python examples/plugins/cdrl.py ROS2_BAG OUT.cdrl``.
"""

import base64
import json

from rosbags.typesys import Stores, get_typestore

from harness.ingest.log_types import Message
from harness.ingest.logs import register_format

STORE = get_typestore(Stores.ROS2_HUMBLE)


class CdrLines:
    """The reader: which files it reads, their topics, their messages one at a time."""

    def detect(self, path):
        """Whether ``path`` is a file of this format."""
        return path.suffix == ".cdrl"

    def topics(self, path):
        """Topic -> (message type, count)."""
        out = {}
        for rec in map(json.loads, path.read_text().splitlines()):
            out[rec["topic"]] = (rec["type"], out.get(rec["topic"], ("", 0))[1] + 1)
        return out

    def messages(self, path, topics):
        """The messages of ``topics``, in the file's order."""
        for rec in map(json.loads, path.read_text().splitlines()):
            if rec["topic"] in topics:
                msg = STORE.deserialize_cdr(base64.b64decode(rec["cdr"]), rec["type"])
                yield Message(rec["topic"], rec["type"], rec["t_ns"], msg)


register_format("cdrl", CdrLines())


if __name__ == "__main__":  # a ROS2 bag rewritten in this format
    import sys
    from pathlib import Path

    from harness.ingest.logs import list_topics, stream

    bag, dest = Path(sys.argv[1]), Path(sys.argv[2])
    dest.parent.mkdir(parents=True, exist_ok=True)
    with dest.open("w") as fh:
        for m in stream(bag, "ros2", tuple(list_topics(bag, "ros2"))):
            cdr = base64.b64encode(STORE.serialize_cdr(m.msg, m.msgtype)).decode()
            rec = {"topic": m.topic, "type": m.msgtype, "t_ns": m.log_ns, "cdr": cdr}
            fh.write(json.dumps(rec) + "\n")

"""Ingesters: NCLT native files, ROS1 bags, ROS2 bags (sqlite3 or mcap storage) and plain MCAP."""

from .logs import detect_format
from .nclt_session import read_nclt_groundtruth
from .session import combine_frames, ingest_session, load_frames

__all__ = [
    "combine_frames",
    "detect_format",
    "ingest_session",
    "load_frames",
    "read_nclt_groundtruth",
]

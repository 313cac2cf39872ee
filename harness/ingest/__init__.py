"""Ingesters: NCLT native files, ROS1 bags, ROS2 bags (sqlite3 or mcap storage) and plain MCAP."""

from harness.ingest.logs import detect_format
from harness.ingest.nclt_session import read_nclt_groundtruth
from harness.ingest.session import combine_frames, ingest_session, load_frames

__all__ = [
    "combine_frames",
    "detect_format",
    "ingest_session",
    "load_frames",
    "read_nclt_groundtruth",
]

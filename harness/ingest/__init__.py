"""Ingesters: NCLT native files, ROS1 bags, ROS2 bags (sqlite3 or mcap storage) and plain MCAP."""

from .logs import detect_format
from .session import ingest_session, load_frames, read_nclt_groundtruth

__all__ = ["detect_format", "ingest_session", "load_frames", "read_nclt_groundtruth"]

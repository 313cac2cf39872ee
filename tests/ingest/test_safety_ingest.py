"""Ingest of damaged or odd logs: non-finite poses, quaternions, salvage, line numbers, JPEG.

Nothing lost, nothing silently wrong: each case goes through the CLI as a user types it where it
can; bad input gives one ``ERROR:`` line, exit 1, and leaves nothing partial behind.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from harness.cli import main
from harness.errors import CorruptLogError, IngestError
from harness.fixture import messages as M
from harness.fixture import writers as W
from harness.ingest import ingest_session, load_frames
from harness.ingest.config import IngestConfig, SessionConfig
from harness.records import Pose

from ..safety_common import _log


def _quat_log(
    tmp: Path,
    q: tuple[float, float, float, float] | None = None,
    pose_utimes: list[int] | None = None,
) -> Path:
    """An MCAP (written by the real mcap and CDR libraries, in this message order) whose 5th pose
    message carries quaternion ``q``; ``pose_utimes`` replaces the pose stamps."""
    from mcap.writer import Writer

    ts = M.ROS2
    path = tmp / "q.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        chans = {}
        for topic, typ in (
            ("/image", "sensor_msgs/msg/Image"),
            ("/pose", "geometry_msgs/msg/PoseStamped"),
        ):
            msgdef, _ = ts.generate_msgdef(typ, ros_version=2)
            sid = w.register_schema(name=typ, encoding="ros2msg", data=msgdef.encode())
            chans[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
        rgb = np.zeros((4, 4, 3), np.uint8)
        for i in range(8):
            t = 1_000_000 + i * 50_000
            msg = M.pose_stamped_msg(
                ts, Pose(pose_utimes[i] if pose_utimes else t, float(i), 0.0, 0.0, 0.0, 0.0, 0.0)
            )
            if i == 4 and q is not None:
                (
                    msg.pose.orientation.x,
                    msg.pose.orientation.y,
                    msg.pose.orientation.z,
                    msg.pose.orientation.w,
                ) = q
            w.add_message(
                chans["/pose"],
                log_time=t * 1000,
                data=bytes(ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped")),
                publish_time=t * 1000,
            )
            if i % 2:
                im = M.image_msg(ts, t, rgb, "rgb8")
                w.add_message(
                    chans["/image"],
                    log_time=t * 1000,
                    data=bytes(ts.serialize_cdr(im, "sensor_msgs/msg/Image")),
                    publish_time=t * 1000,
                )
        w.finish()
    return path


def test_non_finite_poses_are_dropped_and_counted(tmp_path: Path) -> None:
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(12)]
    poses[3] = dataclasses.replace(poses[3], x=float("nan"))
    poses[7] = dataclasses.replace(poses[7], y=float("inf"))
    path = _log(tmp_path, "mcap", poses)
    rep = ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")
    assert rep["dropped"]["non_finite_pose"] == 2
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert np.isfinite(df[["x", "y", "z", "roll", "pitch", "yaw"]].to_numpy()).all()


def test_inf_in_nclt_ground_truth_is_dropped_and_counted(small_world: Path, tmp_path: Path) -> None:
    root = tmp_path / "nclt"
    shutil.copytree(small_world / "nclt", root)
    gt = next((root / "ground_truth").glob("*.csv"))
    session = gt.stem.replace("groundtruth_", "")
    lines = gt.read_text().splitlines()
    parts = lines[5].split(",")
    parts[2] = "inf"
    lines[5] = ",".join(parts)
    gt.write_text("\n".join(lines) + "\n")
    rep = ingest_session(
        SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
    )
    base = ingest_session(
        SessionConfig(name=session, source=str(small_world / "nclt")),
        IngestConfig(),
        tmp_path / "b",
    )
    assert (
        rep["dropped"]["groundtruth_non_finite_rows"]
        == base["dropped"]["groundtruth_non_finite_rows"] + 1
    )


def test_zero_or_euler_quaternions_are_rejected_with_message_and_norm(tmp_path: Path) -> None:
    for q, norm in (((0.0, 0.0, 0.0, 0.0), "norm 0"), ((0.1, 0.2, 1.5, 0.0), "norm 1.51658")):
        with pytest.raises(IngestError, match=rf"/pose message 5.*{norm}, not 1 .*Euler angles"):
            ingest_session(
                SessionConfig(name="s", source=str(_quat_log(tmp_path, q))),
                IngestConfig(),
                tmp_path / "o",
            )
        assert not (tmp_path / "o").exists()


def test_nearly_unit_quaternions_are_normalised_and_counted(tmp_path: Path) -> None:
    rep = ingest_session(
        SessionConfig(name="s", source=str(_quat_log(tmp_path, (0.0, 0.0, 0.0, 1.0005)))),
        IngestConfig(),
        tmp_path / "o",
    )
    assert rep["normalised"]["quaternion_normalised"] == 1 and rep["frames_written"] == 4


def test_corrupt_zstd_chunk_in_mcap_is_a_clear_error(tmp_path: Path) -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(40)]
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(80)]
    path = tmp_path / "z.mcap"
    W.write_mcap(path, frames, poses)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3 : len(raw) // 3 + 64] = b"\xa5" * 64
    path.write_bytes(bytes(raw))
    with pytest.raises((CorruptLogError, IngestError), match=r"z\.mcap"):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")


@pytest.mark.parametrize("compression", ["none", "bz2", "lz4"])
def test_salvage_keeps_the_frames_of_a_truncated_ros1_bag(tmp_path: Path, compression: str) -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    path = tmp_path / "full.bag"
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0, 0, 0, 0, 0) for i in range(40)]
    frames = [W.LogFrame(p.utime, rgb) for p in poses[1::2]]
    W.write_ros1(
        path, frames, poses, compression=compression, chunk_bytes=20_000
    )  # several chunks: whole ones survive
    bad = tmp_path / "trunc.bag"
    bad.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    with pytest.raises(CorruptLogError, match=r"Rerun with --salvage"):
        ingest_session(SessionConfig(name="s", source=str(bad)), IngestConfig(), tmp_path / "o")
    rep = ingest_session(
        SessionConfig(name="s", source=str(bad)), IngestConfig(salvage=True), tmp_path / "o"
    )
    assert 0 < rep["frames_written"] < 20 and "salvaged" in rep


def test_salvage_of_a_ros2_bag_keeps_what_sqlite_can_read_or_says_it_cannot(
    tmp_path: Path,
) -> None:
    path = _log(tmp_path, "ros2", n=30)
    db = next(path.glob("*.db3"))
    (path / "metadata.yaml").unlink()  # rosbags cannot open the bag: the sequential reader must
    rep = ingest_session(
        SessionConfig(name="s", source=str(path), format="ros2"),
        IngestConfig(salvage=True),
        tmp_path / "o",
    )
    assert rep["frames_written"] == 30
    raw = db.read_bytes()
    db.write_bytes(raw[: len(raw) // 2])  # cut: the first leaf page lies past the cut here
    rep = ingest_session(
        SessionConfig(name="s", source=str(path), format="ros2"),
        IngestConfig(salvage=True),
        tmp_path / "o2",
    )
    assert 0 < rep["frames_written"] < 30
    assert "read as zeros skipped" in rep["salvaged"]["detail"]


def test_a_truncated_mcap_is_called_damaged_not_empty(tmp_path: Path) -> None:
    path = _log(tmp_path, "mcap")
    bad = tmp_path / "t.mcap"
    bad.write_bytes(path.read_bytes()[:40])
    with pytest.raises(CorruptLogError, match=r"truncated or corrupt") as ei:
        ingest_session(
            SessionConfig(name="s", source=str(bad)), IngestConfig(salvage=True), tmp_path / "o"
        )
    assert "empty" not in str(ei.value) and "Rerun with --salvage" not in str(ei.value)


def test_annotation_errors_count_blank_lines(tmp_path: Path) -> None:
    from harness.errors import AnnotationError
    from harness.ingest.annotations import load_annotations

    p = tmp_path / "a.csv"
    p.write_text(
        "session,camera,utime,status,x1,y1,x2,y2,label\ns,c,1,no-change,,,,,\n\n\ns,c,2,maybe,,,,,\n"
    )
    with pytest.raises(AnnotationError, match=r"line 5: status must be"):
        load_annotations(p)


def test_nclt_ground_truth_errors_name_the_csv_line(small_world: Path, tmp_path: Path) -> None:
    root = tmp_path / "nclt"
    shutil.copytree(small_world / "nclt", root)
    gt = next((root / "ground_truth").glob("*.csv"))
    session = gt.stem.replace("groundtruth_", "")
    lines = gt.read_text().splitlines()
    nan_lines = [i + 1 for i, line in enumerate(lines) if "nan" in line.lower()]
    k = max(nan_lines) + 3  # a line after the NaN rows, so a row index would differ from the line
    parts = lines[k - 1].split(",")
    parts[0] = "5"
    lines[k - 1] = ",".join(parts)
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError, match=rf"line {k} at utime 5 comes after line {k - 1}"):
        ingest_session(
            SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
        )


def test_pose_message_numbers_are_one_based(tmp_path: Path) -> None:
    stamps = [1_000_000 + i * 50_000 for i in range(8)]
    stamps[2] = 10  # the third pose message goes back in time
    path = _quat_log(tmp_path, pose_utimes=stamps)
    with pytest.raises(
        IngestError, match=r"message 3 at utime 10 comes after message 2 at utime 1050000"
    ):
        ingest_session(
            SessionConfig(name="s", source=str(path)),
            IngestConfig(time_source="header"),
            tmp_path / "o",
        )


def test_verify_images_drops_a_truncated_jpeg(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    import sqlite3

    rgb = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    path = tmp_path / "bag"
    W.write_ros2(
        path,
        [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(6)],
        [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(12)],
        storage="sqlite3",
        image="compressed",
    )
    db = next(path.glob("*.db3"))
    con = sqlite3.connect(db)
    tid = con.execute(
        "SELECT id FROM topics WHERE type = 'sensor_msgs/msg/CompressedImage'"
    ).fetchone()[0]
    rid, data = con.execute(
        "SELECT id, data FROM messages WHERE topic_id = ? ORDER BY id LIMIT 1 OFFSET 2", (tid,)
    ).fetchone()
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    msg = ts.deserialize_cdr(bytes(data), "sensor_msgs/msg/CompressedImage")
    msg.data = msg.data[: int(len(msg.data) * 0.8)]  # the header survives, the body does not
    con.execute(
        "UPDATE messages SET data = ? WHERE id = ?",
        (bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage")), rid),
    )
    con.commit()
    con.close()
    rep = ingest_session(
        SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "plain"
    )
    assert rep["frames_written"] == 6  # the header alone looks fine
    assert (
        main(
            ["ingest", str(path), "--session", "s", "--out", str(tmp_path / "v"), "--verify-images"]
        )
        == 0
    )
    rep = json.loads((tmp_path / "v" / "ingest_report.json").read_text())
    assert rep["dropped"]["corrupt_image"] == 1 and rep["frames_written"] == 5

"""Ingesters: round trips through every log format and a test per bad-input case."""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from harness.errors import CorruptLogError, IngestError, TopicError
from harness.fixture import build_world, render_frame
from harness.fixture import messages as M
from harness.fixture import writers as W
from harness.fixture.generate import FORMATS, session_path
from harness.imagestore import read_image
from harness.ingest import ingest_session, load_frames
from harness.ingest.config import IngestConfig, SessionConfig
from harness.ingest.poses import interpolate
from harness.records import FRAME_COLUMNS, Pose

from ..conftest import SMALL

POSE_COLS = ["x", "y", "z", "roll", "pitch", "yaw"]
LOSSLESS = ("nclt", "ros1", "mcap", "ros2mcap", "mcaptf")


def _ingest(world: Path, fmt: str, session: str, out: Path, **kw: object) -> pd.DataFrame:
    ingest_session(
        SessionConfig(name=session, source=str(world / session_path(fmt, session)), **kw),
        IngestConfig(),
        out,
    )  # type: ignore[arg-type]
    return load_frames(out / "frames.parquet")


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_poses_and_pixels(small_world: Path, tmp_path: Path, fmt: str) -> None:
    truth = pd.read_parquet(small_world / "truth" / "frames.parquet")
    world = build_world(SMALL)
    for si, (session, _) in enumerate(SMALL.sessions):
        df = _ingest(small_world, fmt, session, tmp_path / session)
        tr = truth[truth["session"] == session].reset_index(drop=True)
        assert list(df.columns) == FRAME_COLUMNS
        assert (df["utime"].to_numpy() == tr["utime"].to_numpy()).all()
        np.testing.assert_allclose(
            df[POSE_COLS].to_numpy(), tr[POSE_COLS].to_numpy(), atol=1e-6, rtol=0
        )
        assert (df["width"] == SMALL.width).all() and (df["height"] == SMALL.height).all()
        for fi in (0, len(df) - 1):
            img = read_image(df["image"][fi])
            ref, _ = render_frame(world, si, fi)
            if fmt in LOSSLESS:
                assert np.array_equal(img, ref)
            else:  # JPEG of a noisy image: close, not equal
                assert np.abs(img.astype(int) - ref).mean() < 8


def test_all_formats_give_the_same_frame_table(small_world: Path, tmp_path: Path) -> None:
    session = SMALL.sessions[1][0]
    tables = [
        _ingest(small_world, f, session, tmp_path / f).drop(
            columns=["image", "pose_frame", "pose_of"]
        )
        for f in FORMATS
    ]
    for t in tables[1:]:
        pd.testing.assert_frame_equal(tables[0], t, check_exact=False, atol=1e-9, rtol=0)


def test_report_counts_what_was_read_and_dropped(small_world: Path, tmp_path: Path) -> None:
    import json

    session = SMALL.sessions[0][0]
    _ingest(small_world, "nclt", session, tmp_path / "n")
    rep = json.loads((tmp_path / "n" / "ingest_report.json").read_text())
    assert rep["dropped"]["groundtruth_non_finite_rows"] == 3
    assert rep["frames_written"] == SMALL.frames
    _ingest(small_world, "ros1", session, tmp_path / "r")
    rep = json.loads((tmp_path / "r" / "ingest_report.json").read_text())
    assert rep["messages_read"] == {
        "/camera/image_raw": SMALL.frames,
        "/odom": SMALL.frames * SMALL.pose_rate + 1,
    }


# ------------------------------------------------------------------ pose interpolation


def test_interpolation_linear_and_shortest_arc() -> None:
    pt = np.array([0, 100_000], np.int64)
    pv = np.array([[0, 0, 0, 0, 0, np.radians(170)], [1, 2, 0, 0, 0, np.radians(-170)]], float)
    res = interpolate(pt, pv, np.array([50_000]), 100_000)
    np.testing.assert_allclose(res.poses[0, :2], [0.5, 1.0])
    assert abs(abs(res.poses[0, 5]) - np.pi) < 1e-12  # across +-180, not through 0


def test_interpolation_drops_and_counts() -> None:
    pt = np.array([1_000_000, 1_050_000, 2_000_000], np.int64)
    pv = np.zeros((3, 6))
    img = np.array([900_000, 1_000_000, 1_020_000, 1_500_000, 2_000_000, 2_000_001], np.int64)
    res = interpolate(pt, pv, img, 100_000)
    assert res.keep.tolist() == [False, True, True, False, True, False]
    assert res.dropped == {"before_first_pose": 1, "after_last_pose": 1, "pose_gap": 1}


# ------------------------------------------------------------------ image encodings


def _encoding_log(tmp: Path, encoding: str, image: np.ndarray) -> Path:
    poses = [Pose(t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) for t in (1_000_000, 1_100_000, 1_200_000)]
    frames = [W.LogFrame(1_100_000, image)]
    path = tmp / f"{encoding}.mcap"
    W.write_mcap(path, frames, poses, image="raw", encoding=encoding, pose_kind="pose_cov")
    return path


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8"])
def test_colour_encodings_decode_to_the_same_pixels(tmp_path: Path, encoding: str) -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (9, 7, 3), dtype=np.uint8)
    path = _encoding_log(tmp_path, encoding, rgb)
    df = _frames_of(path, tmp_path / "o")
    got = read_image(df["image"][0])
    want = (
        cv2.cvtColor(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
        if encoding == "mono8"
        else rgb
    )
    assert np.array_equal(got, want)


def _frames_of(path: Path, out: Path) -> pd.DataFrame:
    ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), out)
    return load_frames(out / "frames.parquet")


def test_mono16_keeps_sixteen_bits_in_the_store(tmp_path: Path) -> None:
    raw = (np.arange(6 * 5, dtype=np.uint16).reshape(6, 5) * 2000).astype(np.uint16)
    df = _frames_of(_encoding_log(tmp_path, "mono16", raw), tmp_path / "o")
    stored = cv2.imread(df["image"][0], cv2.IMREAD_UNCHANGED)
    assert stored.dtype == np.uint16 and np.array_equal(stored, raw)
    assert np.array_equal(read_image(df["image"][0])[..., 0], (raw >> 8).astype(np.uint8))


@pytest.mark.parametrize("pattern", ["bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8"])
def test_bayer_is_demosaiced(tmp_path: Path, pattern: str) -> None:
    # a flat colour mosaicked with the pattern must demosaic back to (nearly) that colour
    colour = np.array([200, 100, 40])
    layout = {
        "bayer_rggb8": "RGGB",
        "bayer_bggr8": "BGGR",
        "bayer_gbrg8": "GBRG",
        "bayer_grbg8": "GRBG",
    }[pattern]
    idx = {"R": 0, "G": 1, "B": 2}
    raw = np.empty((8, 8), np.uint8)
    for dy in range(2):
        for dx in range(2):
            raw[dy::2, dx::2] = colour[idx[layout[dy * 2 + dx]]]
    df = _frames_of(_encoding_log(tmp_path, pattern, raw), tmp_path / "o")
    got = read_image(df["image"][0])[2:-2, 2:-2].reshape(-1, 3).mean(0)
    np.testing.assert_allclose(got, colour, atol=2)


def test_compressed_png_is_stored_as_is(tmp_path: Path) -> None:
    """A PNG CompressedImage is kept byte for byte (lossless: the pixels come back exactly).

    JPEG likewise as .jpg.
    """
    rgb = np.random.default_rng(1).integers(0, 256, (10, 12, 3), dtype=np.uint8)
    poses = [Pose(t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) for t in (1_000_000, 1_200_000)]
    W.write_ros2(
        tmp_path / "png",
        [W.LogFrame(1_100_000, rgb)],
        poses,
        storage="sqlite3",
        image="compressed",
        compressed_format="png",
    )
    df = _frames_of(tmp_path / "png", tmp_path / "o")
    assert df["image"][0].endswith(".png") and Path(df["image"][0]).read_bytes().startswith(
        b"\x89PNG"
    )
    assert df["width"][0] == 12 and df["height"][0] == 10
    assert np.array_equal(read_image(df["image"][0]), rgb)
    W.write_ros2(
        tmp_path / "jpg", [W.LogFrame(1_100_000, rgb)], poses, storage="sqlite3", image="compressed"
    )
    assert _frames_of(tmp_path / "jpg", tmp_path / "o2")["image"][0].endswith(".jpg")


# ------------------------------------------------------------------ bad input


def _small_log(tmp: Path, fmt: str, n: int = 6, side: int = 8) -> Path:
    rgb = np.random.default_rng(0).integers(0, 256, (side, side, 3), dtype=np.uint8)
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(n)]
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(2 * n)]
    if fmt == "mcap":
        path = tmp / "log.mcap"
        W.write_mcap(path, frames, poses)
    elif fmt == "ros1":
        path = tmp / "log.bag"
        W.write_ros1(path, frames, poses)
    else:
        path = tmp / "bag"
        W.write_ros2(path, frames, poses, storage="sqlite3")
    return path


def test_truncated_mcap_names_the_damage_and_salvages(tmp_path: Path) -> None:
    path = _small_log(tmp_path, "mcap", n=60, side=160)  # about 4.6 MB: several 1 MiB chunks
    data = path.read_bytes()
    bad = tmp_path / "trunc.mcap"
    bad.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "out"
    with pytest.raises(
        CorruptLogError, match=r"trunc\.mcap.*messages were read before the damage.*--salvage"
    ) as ei:
        ingest_session(SessionConfig(name="s", source=str(bad)), IngestConfig(), out)
    assert not out.exists(), "nothing partial is left after a failure"
    ingest_session(SessionConfig(name="s", source=str(bad)), IngestConfig(salvage=True), out)
    df = load_frames(out / "frames.parquet")
    assert 0 < len(df) < 60
    # the messages mcap's own stream reader gets from the cut file before it fails
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    readable = 0
    with open(bad, "rb") as f, contextlib.suppress(Exception):
        for rec in StreamReader(f).records:
            readable += isinstance(rec, Message)
    assert 0 < ei.value.messages_read == readable


def test_truncated_ros1_bag_is_a_clear_error(tmp_path: Path) -> None:
    path = _small_log(tmp_path, "ros1")
    bad = tmp_path / "trunc.bag"
    bad.write_bytes(path.read_bytes()[:-200])
    with pytest.raises(CorruptLogError, match=r"trunc\.bag"):
        ingest_session(SessionConfig(name="s", source=str(bad)), IngestConfig(), tmp_path / "o")


def test_corrupt_sqlite_bag_is_a_clear_error(tmp_path: Path) -> None:
    path = _small_log(tmp_path, "ros2")
    db = next(path.glob("*.db3"))
    raw = bytearray(db.read_bytes())
    raw[100:4000] = b"\x00" * 3900
    db.write_bytes(bytes(raw))
    with pytest.raises(IngestError, match=str(path.name)):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")


def test_earlier_results_survive_a_failed_rerun(tmp_path: Path) -> None:
    good = _small_log(tmp_path, "mcap")
    out = tmp_path / "out"
    ingest_session(SessionConfig(name="s", source=str(good)), IngestConfig(), out)
    before = (out / "frames.parquet").read_bytes()
    with pytest.raises(TopicError):
        ingest_session(
            SessionConfig(name="s", source=str(good), image_topic="/nope"),
            IngestConfig(),
            out,
            force=True,
        )
    assert (out / "frames.parquet").read_bytes() == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")] == []


def test_missing_topic_lists_the_topics(tmp_path: Path) -> None:
    path = _small_log(tmp_path, "mcap")
    with pytest.raises(TopicError, match=r"'/nope' is not in the log; topics: /camera/image_raw"):
        ingest_session(
            SessionConfig(name="s", source=str(path), image_topic="/nope"),
            IngestConfig(),
            tmp_path / "o",
        )


def test_ambiguous_topics_ask_for_a_flag(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "two.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        for topic in ("/cam_a/image_raw", "/cam_b/image_raw"):
            msgdef, _ = M.ROS2.generate_msgdef("sensor_msgs/msg/Image", ros_version=2)
            sid = w.register_schema("sensor_msgs/msg/Image", "ros2msg", msgdef.encode())
            w.register_channel(topic, "cdr", sid)
        w.finish()
    with pytest.raises(TopicError, match=r"several image topics .*--image-topic"):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")


def test_unknown_encoding_is_named(tmp_path: Path) -> None:
    path = tmp_path / "yuv.mcap"
    poses = [Pose(t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) for t in (1_000_000, 1_200_000)]
    W.write_mcap(path, [W.LogFrame(1_100_000, np.zeros((4, 4), np.uint8))], poses, encoding="mono8")
    # rewrite the encoding field: serialize by hand with a bogus encoding
    msg = M.image_msg(M.ROS2, 1_100_000, np.zeros((4, 4), np.uint8), "mono8")
    msg.encoding = "yuv422_yuy2"
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        ids = {}
        for topic, typ in (
            ("/camera/image_raw", "sensor_msgs/msg/Image"),
            ("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        ):
            msgdef, _ = M.ROS2.generate_msgdef(typ, ros_version=2)
            ids[topic] = w.register_channel(
                topic, "cdr", w.register_schema(typ, "ros2msg", msgdef.encode())
            )
        w.add_message(
            ids["/camera/image_raw"],
            1_100_000_000,
            bytes(M.ROS2.serialize_cdr(msg, "sensor_msgs/msg/Image")),
            1_100_000_000,
        )
        w.finish()
    with pytest.raises(IngestError, match=r"message 1: unsupported image encoding 'yuv422_yuy2'"):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")


def test_empty_log_is_rejected(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "empty.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        w.finish()
    with pytest.raises(IngestError, match=r"empty"):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")


def test_non_monotonic_image_stamps_are_rejected(tmp_path: Path) -> None:
    rgb = np.zeros((4, 4, 3), np.uint8)
    frames = [W.LogFrame(t, rgb) for t in (1_000_000, 1_200_000, 1_100_000)]
    poses = [Pose(1_000_000 + i * 50_000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(6)]
    path = tmp_path / "back.bag"
    # write messages in the given (non-monotonic) order by sorting on a fake log time
    from rosbags.rosbag1 import Writer as Writer1

    with Writer1(path) as w:
        ci = w.add_connection("/camera/image_raw", "sensor_msgs/msg/Image", typestore=M.ROS1)
        co = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=M.ROS1)
        for p in poses:
            w.write(
                co,
                p.utime * 1000,
                M.ROS1.serialize_ros1(M.odometry_msg(M.ROS1, p, True), "nav_msgs/msg/Odometry"),
            )
        for k, f in enumerate(frames):
            w.write(
                ci,
                2_000_000_000 + k,
                M.ROS1.serialize_ros1(
                    M.image_msg(M.ROS1, f.utime, f.image, "rgb8", True), "sensor_msgs/msg/Image"
                ),
            )
    with pytest.raises(
        IngestError,
        match=r"image_raw message 3: image time stamps are not monotonic: utime 1100000 comes "
        r"after utime 1200000",
    ):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")


def test_groundtruth_bad_row_names_the_line(small_world: Path, tmp_path: Path) -> None:
    root = tmp_path / "nclt"
    shutil.copytree(small_world / "nclt", root)
    session = SMALL.sessions[0][0]
    gt = root / "ground_truth" / f"groundtruth_{session}.csv"
    lines = gt.read_text().splitlines()
    lines[7] = lines[7].replace(",", ",abc,", 1).rsplit(",", 1)[0]
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError, match=r"groundtruth_.*line 8: non-numeric"):
        ingest_session(
            SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
        )
    lines[7] = "1,2,3"
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError, match=r"line 8: expected 7 fields"):
        ingest_session(
            SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
        )


def test_nclt_missing_camera_lists_what_exists(small_world: Path, tmp_path: Path) -> None:
    session = SMALL.sessions[0][0]
    with pytest.raises(IngestError, match=r"cameras found for .*Cam5"):
        ingest_session(
            SessionConfig(name=session, source=str(small_world / "nclt"), camera="Cam2"),
            IngestConfig(),
            tmp_path / "o",
        )


def test_tf_with_several_children_needs_a_choice(tmp_path: Path) -> None:
    from harness.fixture.messages import ROS2, tf_msg

    path = tmp_path / "tf.mcap"
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(5)]
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        ids = {}
        for topic, typ in (
            ("/camera/image_raw", "sensor_msgs/msg/Image"),
            ("/tf", "tf2_msgs/msg/TFMessage"),
        ):
            msgdef, _ = ROS2.generate_msgdef(typ, ros_version=2)
            ids[topic] = w.register_channel(
                topic, "cdr", w.register_schema(typ, "ros2msg", msgdef.encode())
            )
        for p in poses:
            for child in ("base_link", "camera"):
                w.add_message(
                    ids["/tf"],
                    p.utime * 1000,
                    bytes(ROS2.serialize_cdr(tf_msg(ROS2, p, child), "tf2_msgs/msg/TFMessage")),
                    p.utime * 1000,
                )
        img = M.image_msg(ROS2, 1_100_000, np.zeros((4, 4, 3), np.uint8), "rgb8")
        w.add_message(
            ids["/camera/image_raw"],
            1_100_000_000,
            bytes(ROS2.serialize_cdr(img, "sensor_msgs/msg/Image")),
            1_100_000_000,
        )
        w.finish()
    # the images' header.frame_id ("camera") is in the tree: its pose is taken, no flag needed
    ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert (
        df["x"][0] == pytest.approx(2.0)
        and df["pose_frame"][0] == "map"
        and df["pose_of"][0] == "camera"
    )
    # tf_child_frame (the older name of camera_frame) picks another frame of the tree
    ingest_session(
        SessionConfig(name="s", source=str(path), tf_child_frame="base_link"),
        IngestConfig(),
        tmp_path / "o2",
    )
    assert load_frames(tmp_path / "o2" / "frames.parquet")["pose_of"][0] == "base_link"
    with pytest.raises(
        IngestError,
        match=r"camera frame 'lidar' \(camera_frame\) is not in the /tf tree; frames: "
        r"\['base_link', 'camera', 'map'\]",
    ):
        ingest_session(
            SessionConfig(name="s", source=str(path), camera_frame="lidar"),
            IngestConfig(),
            tmp_path / "o3",
        )


def test_unknown_format_is_rejected(tmp_path: Path) -> None:
    p = tmp_path / "log.txt"
    p.write_text("hello")
    with pytest.raises(IngestError, match=r"log\.txt: unknown log format"):
        ingest_session(SessionConfig(name="s", source=str(p)), IngestConfig(), tmp_path / "o")


# ------------------------------------------------------------------ inputs that are not what they
# say (issue 26): one error about that file, never a traceback; duplicates and cut lines counted


def _nclt_copy(small_world: Path, tmp: Path) -> tuple[Path, str, Path]:
    root = tmp / "nclt"
    shutil.copytree(small_world / "nclt", root)
    session = SMALL.sessions[0][0]
    return root, session, root / "ground_truth" / f"groundtruth_{session}.csv"


def _png_bomb(path: Path, w: int = 60_000, h: int = 60_000) -> None:
    """A PNG whose header declares ``w x h`` pixels over a few bytes of data."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 16))
        + chunk(b"IEND", b"")
    )


def test_nclt_ground_truth_that_is_not_text_or_not_a_file(
    small_world: Path, tmp_path: Path
) -> None:
    root, session, gt = _nclt_copy(small_world, tmp_path)
    sc = SessionConfig(name=session, source=str(root))
    gt.write_bytes(gt.read_bytes()[:40] + b"\xff\xfe" + gt.read_bytes()[40:])
    with pytest.raises(IngestError, match=r"ground-truth file is not UTF-8 text .*line 1"):
        ingest_session(sc, IngestConfig(), tmp_path / "o")
    gt.unlink()
    gt.mkdir()
    with pytest.raises(IngestError, match=r"ground-truth file is a directory, not a file"):
        ingest_session(sc, IngestConfig(), tmp_path / "o")


def test_salvage_keeps_the_rows_before_a_cut_last_ground_truth_line(
    small_world: Path, tmp_path: Path
) -> None:
    root, session, gt = _nclt_copy(small_world, tmp_path)
    sc = SessionConfig(name=session, source=str(root))
    whole = ingest_session(sc, IngestConfig(), tmp_path / "whole")
    text = gt.read_text()
    gt.write_text(text + text.splitlines()[-1][:9])  # the writer died mid-line
    with pytest.raises(
        IngestError, match=r"line \d+: expected 7 fields .*--salvage keeps the rows"
    ):
        ingest_session(sc, IngestConfig(), tmp_path / "o")
    rep = ingest_session(sc, IngestConfig(salvage=True), tmp_path / "o")
    assert rep["dropped"]["groundtruth_cut_last_line"] == 1 and rep["salvaged"]
    assert rep["frames_written"] == whole["frames_written"]


def test_two_images_with_one_utime_are_one_frame_and_counted(
    small_world: Path, tmp_path: Path
) -> None:
    root, session, _ = _nclt_copy(small_world, tmp_path)
    cam = root / "images" / session / "lb3" / "Cam5"
    first = sorted(cam.iterdir())[0]
    cv2.imwrite(str(first.with_suffix(".png")), cv2.imread(str(first)))
    rep = ingest_session(
        SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
    )
    assert rep["dropped"]["duplicate_image_time"] == 1
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert not df.duplicated(["session", "camera", "utime"]).any()
    assert df.loc[df["utime"] == int(first.stem), "image"].iloc[0].split("#")[0].endswith(".png")


def test_a_decompression_bomb_is_refused_by_its_header(small_world: Path, tmp_path: Path) -> None:
    from harness.ingest.images import compressed_size

    root, session, _ = _nclt_copy(small_world, tmp_path)
    cam = root / "images" / session / "lb3" / "Cam5"
    victim = sorted(cam.iterdir())[2]
    victim.unlink()
    _png_bomb(victim.with_suffix(".png"))
    sc = SessionConfig(name=session, source=str(root))
    with pytest.raises(IngestError, match=r"declares 60000 x 60000 = 3,600,000,000 pixels"):
        ingest_session(sc, IngestConfig(), tmp_path / "o")
    rep = ingest_session(sc, IngestConfig(max_image_pixels=4_000_000_000), tmp_path / "o")
    assert rep["frames_written"] > 0  # a real image that large: raise the limit
    _png_bomb(tmp_path / "b.png")
    with pytest.raises(IngestError, match=r"message 3: the image declares"):
        compressed_size((tmp_path / "b.png").read_bytes(), "message 3")


def test_an_unreadable_log_is_called_unreadable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os

    log = _small_log(tmp_path, "mcap")
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, m: False if Path(p) == log else real(p, m))
    with pytest.raises(
        IngestError, match=r"log of session S is not readable \(permission denied\)"
    ):
        ingest_session(SessionConfig(name="S", source=str(log)), IngestConfig(), tmp_path / "o")


def _sqlite_bag(tmp_path: Path, n: int) -> tuple[Path, list, Path]:
    """A ROS2 sqlite3 bag of ``n`` raw 48x64 frames and 2n poses: (bag, frames, its .db3)."""
    rgb = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(n)]
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(2 * n)]
    path = tmp_path / "bag"
    W.write_ros2(path, frames, poses, storage="sqlite3", image="raw")
    return path, frames, next(path.glob("*.db3"))


def test_salvage_of_a_sqlite_bag_damaged_in_the_middle_keeps_the_rows_beyond(
    tmp_path: Path,
) -> None:
    """A 95%-intact ROS2 sqlite bag ("database disk image is malformed" mid-table): the rows on the
    intact pages before and after the damage are kept; without --salvage, one clear error."""
    n = 40
    path, _, db = _sqlite_bag(tmp_path, n)
    raw = bytearray(db.read_bytes())
    page = int.from_bytes(raw[16:18], "big") or 65536
    leaves = [i for i in range(1, len(raw) // page) if raw[i * page] == 0x0D]  # table b-tree leaves
    mid = leaves[len(leaves) // 2]
    raw[mid * page : mid * page + 12] = b"\x0d\xff\xff\xff\xff\x00\x00\xff" + b"\x00" * 4
    db.write_bytes(bytes(raw))
    sc = SessionConfig(name="s", source=str(path), format="ros2")
    with pytest.raises(CorruptLogError):
        ingest_session(sc, IngestConfig(), tmp_path / "o")
    rep = ingest_session(sc, IngestConfig(salvage=True), tmp_path / "o")
    assert "row(s) skipped" in rep["salvaged"]["detail"]
    assert n // 2 < rep["frames_written"] < n  # more than the rows before the damage


@pytest.mark.parametrize("cut", [0.40, 0.83, 0.95])
def test_salvage_of_a_sqlite_bag_cut_short_keeps_the_rows_before_the_cut(
    tmp_path: Path, cut: float
) -> None:
    """A ROS2 sqlite bag cut while it was written (at 40%, at a page boundary near 83%, at 95%):
    sqlite refuses the whole file ("database disk image is malformed", the header counts more
    pages than there are), yet the rows before the cut are there. With --salvage they are kept:
    the frames read are the first frames of the intact bag, and a longer file keeps more."""
    from harness.ingest.session import load_frames

    n = 40
    path, frames, db = _sqlite_bag(tmp_path, n)
    raw = db.read_bytes()
    page = int.from_bytes(raw[16:18], "big")
    end = int(len(raw) * cut)
    if cut == 0.83:
        end -= end % page
    db.write_bytes(raw[:end])
    sc = SessionConfig(name="s", source=str(path), format="ros2")
    with pytest.raises(CorruptLogError, match="malformed"):
        ingest_session(sc, IngestConfig(), tmp_path / "o")
    rep = ingest_session(sc, IngestConfig(salvage=True), tmp_path / "o")
    kept = load_frames(tmp_path / "o" / "frames.parquet")["utime"].tolist()
    assert rep["frames_written"] == len(kept) > 0
    # a prefix of the bag's own frames (minus the last, whose later pose may be lost to the cut)
    assert kept == [f.utime for f in frames[: len(kept)]]
    assert len(kept) >= int(n * cut) - 3, (cut, len(kept))
    assert "cut off" in rep["salvaged"]["detail"]

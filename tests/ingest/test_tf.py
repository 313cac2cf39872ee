"""Robot logs as robots record them (method §3): camera poses composed through /tf and
/tf_static, per-transform gap rules, clear errors where the path breaks, real-world message quirks,
and ``harness inspect``. Every log here is written by rosbags or the mcap library."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from harness.cli import main
from harness.errors import IngestError
from harness.fixture import messages as M
from harness.fixture import writers as W
from harness.ingest import ingest_session, load_frames
from harness.ingest.config import IngestConfig, SessionConfig
from harness.records import Pose

T0 = 1_700_000_000_000_000  # µs
ODOM = (10.0, 5.0, math.radians(30))  # map -> odom: x, y, yaw (constant, published at 2 Hz)
MOUNT = (0.5, -0.2, 1.0, math.radians(90))  # base_link -> camera_left: a side camera, static


def _transform(ts, t_us: int, parent: str, child: str, x: float, y: float, z: float, yaw: float):
    T = ts.types
    return T["geometry_msgs/msg/TransformStamped"](
        header=M._header(ts, t_us, parent, False),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
            rotation=T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        ),
    )


def _tf(ts, *transforms):
    return ts.types["tf2_msgs/msg/TFMessage"](transforms=list(transforms))


def write_robot_bag(
    path: Path,
    *,
    odom_hole: tuple[float, float] | None = None,
    with_mount: bool = True,
    slash: str = "/",
    seconds: float = 4.0,
    image_format: str | None = None,
    map_odom: float | None = None,
) -> Path:
    """A ROS2 bag as a Nav2 robot records it: /tf holds map -> odom (2 Hz, from localization) and
    odom -> base_link (20 Hz, wheel odometry: x = s metres, yaw = 0.1 s radians at s seconds);
    /tf_static holds the camera mount; images at 5 Hz in frame ``camera_left``."""
    ts = M.ROS2
    tf_t, tfs_t = f"{slash}tf", f"{slash}tf_static"
    img_t = f"{slash}camera_left/image_raw" + ("/compressed" if image_format else "")
    img_type = "sensor_msgs/msg/CompressedImage" if image_format else "sensor_msgs/msg/Image"
    msgs = []
    if with_mount:
        msgs.append((T0, tfs_t, _tf(ts, _transform(ts, T0, "base_link", "camera_left", *MOUNT))))
    for k in range(int(seconds * 2) + 1):
        t = T0 + k * 500_000
        msgs.append(
            (
                t,
                tf_t,
                _tf(
                    ts,
                    _transform(
                        ts,
                        t,
                        "map",
                        "odom",
                        ODOM[0] if map_odom is None else map_odom,
                        ODOM[1],
                        0.0,
                        ODOM[2],
                    ),
                ),
            )
        )
    for k in range(int(seconds * 20) + 1):
        s = k * 0.05
        if odom_hole and odom_hole[0] < s < odom_hole[1]:
            continue
        t = T0 + k * 50_000
        msgs.append(
            (t, tf_t, _tf(ts, _transform(ts, t, "odom", "base_link", s, 0.0, 0.0, 0.1 * s)))
        )
    rgb = smooth_image()
    for k in range(1, int(seconds * 5)):
        t = T0 + k * 200_000 + 30_000  # between odometry samples: interpolated
        if image_format:
            msg = M.compressed_msg(
                ts,
                t,
                rgb,
                "png" if "png" in image_format or "rgb8; compressed" in image_format else "jpeg",
            )
            msg.format = image_format
        else:
            msg = M.image_msg(ts, t, rgb, "rgb8")
        msg.header.frame_id = "camera_left"
        msgs.append((t, img_t, msg))
    msgs.sort(key=lambda m: m[0])
    with Writer2(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conns = {
            tf_t: w.add_connection(tf_t, "tf2_msgs/msg/TFMessage", typestore=ts),
            img_t: w.add_connection(img_t, img_type, typestore=ts),
        }
        if with_mount:
            conns[tfs_t] = w.add_connection(tfs_t, "tf2_msgs/msg/TFMessage", typestore=ts)
        for t, topic, msg in msgs:
            w.write(
                conns[topic],
                t * 1000,
                ts.serialize_cdr(
                    msg, "tf2_msgs/msg/TFMessage" if "tf" in topic.split("/")[-1] else img_type
                ),
            )
    return path


def smooth_image() -> np.ndarray:
    """A 32 x 24 colour gradient (JPEG keeps it within a few levels)."""
    yy, xx = np.mgrid[0:24, 0:32]
    return np.stack([xx * 8, yy * 10, (xx + yy) * 4], -1).astype(np.uint8)


def expected_camera_pose(t_us: int) -> tuple[float, float, float, float]:
    """By hand: camera in odom = base pose composed with the mount; then odom in map."""
    s = (t_us - T0) / 1e6
    xb, yb, yawb = s, 0.0, 0.1 * s
    mx, my, mz, myaw = MOUNT
    px = xb + math.cos(yawb) * mx - math.sin(yawb) * my
    py = yb + math.sin(yawb) * mx + math.cos(yawb) * my
    ox, oy, oyaw = ODOM
    X = ox + math.cos(oyaw) * px - math.sin(oyaw) * py
    Y = oy + math.sin(oyaw) * px + math.cos(oyaw) * py
    yaw = (oyaw + yawb + myaw + math.pi) % (2 * math.pi) - math.pi
    return X, Y, mz, yaw


@pytest.mark.parametrize("flags", [{}, {"fixed_frame": "map"}])
def test_camera_pose_composed_through_the_tree_by_hand(tmp_path: Path, flags: dict) -> None:
    bag = write_robot_bag(tmp_path / "robot")
    rep = ingest_session(
        SessionConfig(name="s", source=str(bag), **flags), IngestConfig(), tmp_path / "o"
    )
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert len(df) == 19 and rep["frames_written"] == 19
    for r in df.itertuples():
        x, y, z, yaw = expected_camera_pose(int(r.utime))
        assert math.hypot(r.x - x, r.y - y) < 1e-3 and abs(r.z - z) < 1e-3  # 1 mm
        assert abs((r.yaw - yaw + math.pi) % (2 * math.pi) - math.pi) < 1e-3  # 1 mrad
        assert abs(r.roll) < 1e-3 and abs(r.pitch) < 1e-3
    # the side camera looks 90 degrees left of the base: pairing uses the camera's heading
    assert df["pose_frame"].unique().tolist() == ["map"] and df["pose_of"].unique().tolist() == [
        "camera_left"
    ]
    tf = rep["tf"]
    assert (
        tf["path"] == ["map->odom", "odom->base_link", "base_link->camera_left"]
        and tf["fixed_frame"] == "map"
    )
    assert tf["transforms"]["map->odom"]["gap_s"] == 1.0  # slow (2 Hz): max_tf_gap_s
    assert tf["transforms"]["odom->base_link"]["gap_s"] == 0.1  # fast (20 Hz): max_pose_gap_s
    assert (
        tf["transforms"]["base_link->camera_left"]["static"]
        and rep["topics"]["pose_source"] == "tf"
    )


def test_each_transform_has_its_own_gap_rule_and_drops_are_counted_by_transform(
    tmp_path: Path,
) -> None:
    bag = write_robot_bag(
        tmp_path / "robot", odom_hole=(1.0, 2.0)
    )  # wheel odometry silent for a second
    rep = ingest_session(SessionConfig(name="s", source=str(bag)), IngestConfig(), tmp_path / "o")
    assert rep["dropped"]["tf odom->base_link: pose_gap"] == 5 and rep["frames_written"] == 14
    # a 2 Hz localization no longer bridges its own 0.5 s gaps: every image loses its pose, under
    # that transform's name
    with pytest.raises(
        IngestError,
        match=r"none of the 19 images got a pose from /tf.*'tf map->odom: pose_gap': 19",
    ):
        ingest_session(
            SessionConfig(name="s", source=str(bag)),
            IngestConfig(max_tf_gap_s=0.2),
            tmp_path / "o2",
        )


def test_a_break_in_the_path_names_the_missing_transform(tmp_path: Path) -> None:
    bag = write_robot_bag(
        tmp_path / "robot", with_mount=False
    )  # no /tf_static: the camera is not in the tree
    with pytest.raises(
        IngestError,
        match=r"camera frame 'camera_left' \(the images' header.frame_id\) is not in the /tf tree",
    ):
        ingest_session(SessionConfig(name="s", source=str(bag)), IngestConfig(), tmp_path / "o")
    with pytest.raises(
        IngestError,
        match=r"no path from 'odom' to 'odom'|fixed_frame 'world' is not in the /tf tree",
    ):
        ingest_session(
            SessionConfig(name="s", source=str(bag), fixed_frame="world", camera_frame="base_link"),
            IngestConfig(),
            tmp_path / "o",
        )
    with pytest.raises(
        IngestError, match=r"no path from 'odom' to 'map'.*missing transform: \? -> map"
    ):
        ingest_session(
            SessionConfig(name="s", source=str(bag), fixed_frame="odom", camera_frame="map"),
            IngestConfig(),
            tmp_path / "o",
        )
    ingest_session(
        SessionConfig(name="s", source=str(bag), camera_frame="base_link"),
        IngestConfig(),
        tmp_path / "o",
    )
    assert load_frames(tmp_path / "o" / "frames.parquet")["pose_of"][0] == "base_link"


def test_topic_names_without_a_leading_slash(tmp_path: Path) -> None:
    bag = write_robot_bag(tmp_path / "robot", slash="")
    rep = ingest_session(SessionConfig(name="s", source=str(bag)), IngestConfig(), tmp_path / "o")
    assert (
        rep["frames_written"] == 19 and rep["tf"]["transforms"]["base_link->camera_left"]["static"]
    )


@pytest.mark.parametrize(
    "fmt", ["jpg", "jpeg", "png", "bgr8; jpeg compressed bgr8", "rgb8; compressed rgb8"]
)
def test_compressed_image_format_strings_as_drivers_write_them(tmp_path: Path, fmt: str) -> None:
    bag = write_robot_bag(tmp_path / "robot", image_format=fmt, seconds=2.0)
    ingest_session(
        SessionConfig(name="s", source=str(bag)), IngestConfig(verify_images=True), tmp_path / "o"
    )
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert len(df) == 9 and (df["width"] == 32).all() and (df["height"] == 24).all()
    from harness.imagestore import read_image

    rgb = smooth_image()
    got = read_image(df["image"][0])
    assert got.shape == (24, 32, 3)
    if "png" in fmt or "rgb8; compressed" in fmt:
        assert df["image"][0].endswith(".png") and np.array_equal(got, rgb)
    else:
        assert df["image"][0].endswith(".jpg") and np.abs(got.astype(int) - rgb).mean() < 4


@pytest.mark.parametrize("compression", ["bz2", "lz4"])
def test_ros1_bags_with_compressed_chunks(tmp_path: Path, compression: str) -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    path = tmp_path / "c.bag"
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0, 0, 0, 0, 0) for i in range(20)]
    W.write_ros1(
        path, [W.LogFrame(p.utime, rgb) for p in poses[1::2]], poses, compression=compression
    )
    assert f"compression={compression}".encode() in path.read_bytes()  # the chunk headers name it
    rep = ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert rep["frames_written"] == 10 and df["x"].tolist() == [float(i) for i in range(1, 20, 2)]
    from harness.imagestore import read_image

    assert np.array_equal(read_image(df["image"][0]), rgb)


def test_rosbag2_split_into_several_files(tmp_path: Path) -> None:
    """A bag recorded with --max-bag-size: two .db3 files listed in one metadata.yaml."""
    rgb = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(24)]
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(12)]
    W.write_ros2(tmp_path / "a", frames[:6], poses[:12], storage="sqlite3")
    W.write_ros2(tmp_path / "b", frames[6:], poses[12:], storage="sqlite3")
    bag = tmp_path / "split"
    bag.mkdir()
    shutil.copy(next((tmp_path / "a").glob("*.db3")), bag / "split_0.db3")
    shutil.copy(next((tmp_path / "b").glob("*.db3")), bag / "split_1.db3")
    ma = yaml.safe_load((tmp_path / "a" / "metadata.yaml").read_text())
    mb = yaml.safe_load((tmp_path / "b" / "metadata.yaml").read_text())
    info, info_b = ma["rosbag2_bagfile_information"], mb["rosbag2_bagfile_information"]
    info["relative_file_paths"] = ["split_0.db3", "split_1.db3"]
    info["files"] = [
        {**info["files"][0], "path": "split_0.db3"},
        {**info_b["files"][0], "path": "split_1.db3"},
    ]
    info["message_count"] += info_b["message_count"]
    info["duration"]["nanoseconds"] = (
        info_b["starting_time"]["nanoseconds_since_epoch"]
        + info_b["duration"]["nanoseconds"]
        - info["starting_time"]["nanoseconds_since_epoch"]
    )
    counts = {
        t["topic_metadata"]["name"]: t["message_count"] for t in info_b["topics_with_message_count"]
    }
    for t in info["topics_with_message_count"]:
        t["message_count"] += counts[t["topic_metadata"]["name"]]
    (bag / "metadata.yaml").write_text(yaml.safe_dump(ma))
    rep = ingest_session(SessionConfig(name="s", source=str(bag)), IngestConfig(), tmp_path / "o")
    assert rep["frames_written"] == 12  # both files, in time order


def test_time_stamps_near_zero_from_a_simulated_clock(tmp_path: Path) -> None:
    rgb = np.zeros((8, 8, 3), np.uint8)
    poses = [
        Pose(i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(20)
    ]  # sim time from 0 s
    frames = [W.LogFrame(25_000 + i * 100_000, rgb) for i in range(9)]
    W.write_mcap(tmp_path / "sim.mcap", frames, poses)
    rep = ingest_session(
        SessionConfig(name="s", source=str(tmp_path / "sim.mcap")), IngestConfig(), tmp_path / "o"
    )
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert (
        rep["frames_written"] == 9
        and df["utime"].tolist()[0] == 25_000
        and df["x"][0] == pytest.approx(0.5)
    )


def test_inspect_prints_topics_and_the_tree_of_every_log(
    small_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    bag = write_robot_bag(tmp_path / "robot")
    logs = [
        bag,
        small_world / "nclt",
        *sorted((small_world / "ros1").glob("*.bag"))[:1],
        *sorted((small_world / "ros2").iterdir())[:1],
        *sorted((small_world / "mcap").glob("*.mcap"))[:1],
        *sorted((small_world / "ros2mcap").iterdir())[:1],
        *sorted((small_world / "mcaptf").glob("*.mcap"))[:1],
    ]
    for log in logs:
        assert main(["inspect", str(log)]) == 0, log
        out = capsys.readouterr().out
        assert "Config lines that would ingest it" in out
        if log.name != "nclt":
            assert "Topics" in out and "Images" in out
    assert main(["inspect", str(bag), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {(e["parent"], e["child"], e["static"]) for e in info["tf"]} == {
        ("map", "odom", False),
        ("odom", "base_link", False),
        ("base_link", "camera_left", True),
    }
    rates = {e["child"]: e["rate_hz"] for e in info["tf"]}
    assert rates["odom"] == pytest.approx(2.0) and rates["base_link"] == pytest.approx(20.0)
    assert (
        info["tf_roots"] == ["map"] and 'camera_frame = "camera_left"' in info["suggested_config"]
    )
    assert info["images"]["/camera_left/image_raw"] == {
        "frame_id": "camera_left",
        "encoding": "rgb8",
        "width": 32,
        "height": 24,
    }
    # the suggested lines ingest the log as they are
    import tomllib

    sess = tomllib.loads(info["suggested_config"])["sessions"][0]
    sess.pop("season")
    ingest_session(SessionConfig(**sess), IngestConfig(), tmp_path / "o")
    assert main(["inspect", str(tmp_path / "nope.bag")]) == 1


def test_tf_flags_as_a_user_types_them(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """--fixed-frame, --camera-frame and --max-tf-gap reach the ingester through the CLI."""
    bag = write_robot_bag(tmp_path / "robot")
    base = ["ingest", str(bag), "--session", "s"]
    assert (
        main(
            [
                *base,
                "--out",
                str(tmp_path / "a"),
                "--fixed-frame",
                "odom",
                "--camera-frame",
                "base_link",
            ]
        )
        == 0
    )
    rep = json.loads((tmp_path / "a" / "ingest_report.json").read_text())
    assert rep["tf"]["path"] == ["odom->base_link"] and rep["pose_frames"] == {
        "pose_frame": "odom",
        "pose_of": "base_link",
    }
    df = load_frames(tmp_path / "a" / "frames.parquet")
    s = (df["utime"][0] - T0) / 1e6
    assert df["x"][0] == pytest.approx(s, abs=1e-3)  # base_link in odom: x = s metres
    capsys.readouterr()
    assert (
        main([*base, "--out", str(tmp_path / "b"), "--max-tf-gap", "0.2"]) == 1
    )  # 2 Hz map -> odom no longer bridged
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") and "tf map->odom: pose_gap" in err
    assert main([*base, "--out", str(tmp_path / "c"), "--max-tf-gap", "0"]) == 1
    assert "--max-tf-gap = 0.0 is out of range; allowed: > 0 seconds" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "d"), "--camera-frame", "lidar"]) == 1
    assert "camera frame 'lidar' (camera_frame) is not in the /tf tree" in capsys.readouterr().err


def test_a_transform_that_is_all_nan_drops_its_frames_and_never_re_roots(tmp_path: Path) -> None:
    """map -> odom of NaN everywhere: the tree keeps its root (map), no frame gets a pose."""
    bag = write_robot_bag(tmp_path / "bag", map_odom=float("nan"))
    with pytest.raises(IngestError, match=r"got a pose from /tf \(map -> camera_left\)") as err:
        ingest_session(SessionConfig(name="s", source=str(bag)), IngestConfig(), tmp_path / "o")
    assert "tf map->odom: no_finite_sample" in str(err.value)
    assert "non_finite_transform" in str(err.value)


def test_a_tf_loop_is_named_as_a_loop(tmp_path: Path) -> None:
    ts = M.ROS2
    path = tmp_path / "loop"
    with Writer2(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        img = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        for k in range(4):
            t = T0 + k * 100_000
            loop = [_transform(ts, t, p, c, 0.0, 0.0, 0.0, 0.0) for p, c in ("ab", "bc", "ca")]
            w.write(tf, t * 1000, ts.serialize_cdr(_tf(ts, *loop), "tf2_msgs/msg/TFMessage"))
            msg = M.image_msg(ts, t + 50_000, smooth_image(), "rgb8")
            msg.header.frame_id = "a"
            w.write(img, (t + 50_000) * 1000, ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    with pytest.raises(
        IngestError, match=r"has no root: its transforms form a loop \(a->b, b->c, c->a\)"
    ):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")

"""Any robot's data: folders of images with TUM, KITTI or EuRoC trajectories (method §13's input).

The fixture's ROS2 bag is written out as a folder of its own image files with its own poses in
each trajectory format, following evo's documented conventions (TUM: seconds and x y z qx qy qz
qw; KITTI: the 3x4 camera pose in the camera frame, x right, y down, z forward, one per image
with times.txt; EuRoC: ns and w first). Each folder must ingest to the same frames (times, poses,
sizes, pixels) as the bag.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.errors import IngestError
from harness.imagestore import read_image
from harness.ingest import ingest_session, logs
from harness.ingest.config import IngestConfig, SessionConfig

COLS = ["utime", "x", "y", "z", "roll", "pitch", "yaw", "width", "height"]


def _bag(small_world: Path) -> Path:
    return sorted((small_world / "ros2").iterdir())[0]


def _messages(bag: Path) -> tuple[list[tuple[int, bytes, str]], list[tuple[int, list[float]]]]:
    """(header ns, bytes, format) of every image, (header ns, x y z qx qy qz qw) of every pose."""
    topics = logs.list_topics(bag, "ros2")
    images, poses = [], []
    for m in logs.stream(bag, "ros2", tuple(topics)):
        t = int(m.msg.header.stamp.sec) * 1_000_000_000 + int(m.msg.header.stamp.nanosec)
        if m.msgtype.endswith("CompressedImage"):
            images.append((t, bytes(m.msg.data), str(m.msg.format)))
        elif m.msgtype.endswith("PoseStamped"):
            p, q = m.msg.pose.position, m.msg.pose.orientation
            poses.append((t, [p.x, p.y, p.z, q.x, q.y, q.z, q.w]))
    assert images and poses
    return images, poses


def _suffix(fmt: str) -> str:
    return ".png" if "png" in fmt else ".jpg"


def _ingest(src: Path, out: Path, name: str) -> tuple[dict, pd.DataFrame]:
    rep = ingest_session(SessionConfig(name=name, source=str(src)), IngestConfig(), out)
    return rep, pd.read_parquet(out / "frames.parquet")


def _same_frames(tmp: Path, fa: pd.DataFrame, fb: pd.DataFrame, a: str, b: str) -> None:
    assert len(fa) == len(fb) > 0
    pd.testing.assert_frame_equal(
        fa[COLS].reset_index(drop=True), fb[COLS].reset_index(drop=True), atol=1e-9, rtol=0
    )
    for ia, ib in zip(fa["image"], fb["image"], strict=True):
        assert np.array_equal(read_image(str(tmp / a / ia)), read_image(str(tmp / b / ib)))


def test_a_tum_folder_ingests_to_the_frames_of_the_same_images_in_a_ros2_bag(
    small_world: Path, tmp_path: Path
) -> None:
    bag = _bag(small_world)
    images, poses = _messages(bag)
    folder = tmp_path / "tum"
    (folder / "rgb").mkdir(parents=True)
    for t, data, fmt in images:  # times from the file names: seconds with nine decimals
        (folder / "rgb" / f"{t // 10**9}.{t % 10**9:09d}{_suffix(fmt)}").write_bytes(data)
    (folder / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        + "".join(
            f"{t // 10**9}.{t % 10**9:09d} " + " ".join(repr(v) for v in vals) + "\n"
            for t, vals in poses
        )
    )
    assert logs.detect_format(folder) == "tum"
    ra, fa = _ingest(bag, tmp_path / "a", bag.name)
    rb, fb = _ingest(folder, tmp_path / "b", bag.name)
    assert rb["format"] == "tum" and rb["dropped"] == ra["dropped"]
    _same_frames(tmp_path, fa, fb, "a", "b")
    # the same gap rule: a hole in the trajectory drops (and counts) the frames inside it
    lines = (folder / "groundtruth.txt").read_text().splitlines()
    (folder / "groundtruth.txt").write_text("\n".join(lines[:20] + lines[40:]) + "\n")
    rc, fc = _ingest(folder, tmp_path / "c", bag.name)
    assert len(fc) < len(fb) and sum(rc["dropped"].values()) == len(fb) - len(fc)


def _rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, s_p, cy, sy = (
        math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw),
        math.sin(yaw),
    )  # fmt: skip
    return np.array(
        [
            [cy * cp, cy * s_p * sr - sy * cr, cy * s_p * cr + sy * sr],
            [sy * cp, sy * s_p * sr + cy * cr, sy * s_p * cr - cy * sr],
            [-s_p, cp * sr, cp * cr],
        ]
    )


def test_a_kitti_folder_ingests_to_the_same_frames_in_the_kitti_camera_frame(
    small_world: Path, tmp_path: Path
) -> None:
    bag = _bag(small_world)
    images, _ = _messages(bag)
    _, fa = _ingest(bag, tmp_path / "a", bag.name)
    folder = tmp_path / "kitti"
    (folder / "image_2").mkdir(parents=True)
    # KITTI's camera axes (x right, y down, z forward) in a z-up world (x forward, y left, z up)
    c = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    times, rows = [], []
    by_t = {t: (data, fmt) for t, data, fmt in images}
    for i, r in enumerate(fa.itertuples()):
        data, fmt = by_t[int(r.utime) * 1000]
        (folder / "image_2" / f"{i:06d}{_suffix(fmt)}").write_bytes(data)
        times.append(f"{int(r.utime) // 10**6}.{int(r.utime) % 10**6:06d}")
        rot = c.T @ _rpy_matrix(r.roll, r.pitch, r.yaw) @ c  # the body axes as camera axes
        pos = c.T @ np.array([r.x, r.y, r.z])
        rows.append(" ".join(f"{v:.17g}" for v in np.hstack([rot, pos[:, None]]).ravel()))
    (folder / "times.txt").write_text("\n".join(times) + "\n")
    (folder / "poses.txt").write_text("\n".join(rows) + "\n")
    assert logs.detect_format(folder) == "kitti"
    rb, fb = _ingest(folder, tmp_path / "b", bag.name)
    assert rb["format"] == "kitti"
    _same_frames(tmp_path, fa, fb, "a", "b")


def test_an_euroc_folder_reads_ns_times_and_w_first_quaternions(
    small_world: Path, tmp_path: Path
) -> None:
    bag = _bag(small_world)
    images, poses = _messages(bag)
    root = tmp_path / "euroc" / "mav0"
    (root / "cam0" / "data").mkdir(parents=True)
    (root / "state_groundtruth_estimate0").mkdir()
    lines = ["#timestamp [ns],filename"]
    for t, data, fmt in images:
        name = f"{t}{_suffix(fmt)}"
        (root / "cam0" / "data" / name).write_bytes(data)
        lines.append(f"{t},{name}")
    (root / "cam0" / "data.csv").write_text("\n".join(lines) + "\n")
    (root / "state_groundtruth_estimate0" / "data.csv").write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
        "q_RS_z []\n"
        + "".join(
            f"{t},{v[0]!r},{v[1]!r},{v[2]!r},{v[6]!r},{v[3]!r},{v[4]!r},{v[5]!r}\n"
            for t, v in poses
        )
    )
    assert logs.detect_format(tmp_path / "euroc") == "euroc"
    _, fa = _ingest(bag, tmp_path / "a", bag.name)
    rb, fb = _ingest(tmp_path / "euroc", tmp_path / "b", bag.name)
    assert rb["format"] == "euroc"
    _same_frames(tmp_path, fa, fb, "a", "b")


def test_a_broken_trajectory_is_one_ingest_error_naming_the_line(tmp_path: Path) -> None:
    folder = tmp_path / "tum"
    (folder / "rgb").mkdir(parents=True)
    (folder / "groundtruth.txt").write_text("1.0 1 2 3 0 0 0\n")  # seven fields
    with pytest.raises(IngestError, match=r"groundtruth.txt: line 1: 7 fields"):
        _ingest(folder, tmp_path / "o", "s")
    k = tmp_path / "kitti"
    (k / "image_2").mkdir(parents=True)
    (k / "image_2" / "000000.png").write_bytes(b"")
    (k / "times.txt").write_text("0.0\n0.1\n")
    (k / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(IngestError, match=r"1 images in image_2/ but 2 lines in times.txt"):
        _ingest(k, tmp_path / "o2", "s")


@pytest.mark.parametrize(
    ("gt_line", "message"),
    [
        ("10,1,2,3,1,0,0", r"data.csv: line 3: 7 fields; EuRoC needs at least 8"),
        ("1.5e9,1,2,3,1,0,0,0", r"data.csv: line 3: '1.5e9' is not a time in integer nanoseconds"),
        ("10,1,2,x,1,0,0,0", r"data.csv: line 3: 'x' is not a number"),
        ("10,1,2,nan,1,0,0,0", r"data.csv: line 3: 'nan' is not finite"),
    ],
)
def test_a_malformed_euroc_file_is_one_ingest_error_naming_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, gt_line: str, message: str
) -> None:
    """Line numbers as an editor counts them: the header is line 1, the bad row line 3."""
    from harness.cli import main

    from ..conftest import one_error

    root = tmp_path / "euroc" / "mav0"
    (root / "cam0" / "data").mkdir(parents=True)
    (root / "state_groundtruth_estimate0").mkdir()
    (root / "cam0" / "data" / "0.png").write_bytes(b"")
    gt = root / "state_groundtruth_estimate0" / "data.csv"
    gt.write_text(
        "#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z\n0,0,0,0,1,0,0,0\n" + gt_line + "\n"
    )
    with pytest.raises(IngestError, match=message):
        _ingest(tmp_path / "euroc", tmp_path / "o", "s")
    # and through the command line: one ERROR line, exit 1, nothing written
    out = tmp_path / "cli"
    assert main(["ingest", str(tmp_path / "euroc"), "--session", "s", "--out", str(out)]) == 1
    err = one_error(capsys)
    assert "line 3" in err and str(gt) in err
    assert not (out / "frames.parquet").exists()


@pytest.mark.parametrize(
    ("stems", "utimes"),
    [  # EuRoC's ns, then us, ms and whole seconds since the epoch, each read by its size
        (["1403715273262142976", "1403715273312142976"], [1403715273262142, 1403715273312142]),
        (["1403715273262142", "1403715273312142"], [1403715273262142, 1403715273312142]),
        (["1403715273262", "1403715273312"], [1403715273262000, 1403715273312000]),
        (["1403715273", "1403715274"], [1403715273000000, 1403715274000000]),
    ],
)
def test_an_image_folder_named_by_integer_times_reads_them_by_their_size(
    tmp_path: Path, stems: list[str], utimes: list[int]
) -> None:
    import cv2

    folder = tmp_path / "cam"
    folder.mkdir()
    for s in stems:
        cv2.imwrite(str(folder / f"{s}.png"), np.full((8, 12, 3), 100, np.uint8))
    _, fr = _ingest(folder, tmp_path / "o", "s")
    assert fr["utime"].tolist() == utimes


def test_a_file_name_past_int64_nanoseconds_is_one_ingest_error_naming_it(tmp_path: Path) -> None:
    import cv2

    folder = tmp_path / "cam"
    folder.mkdir()
    name = "99999999999999999999"
    cv2.imwrite(str(folder / f"{name}.png"), np.full((8, 12, 3), 100, np.uint8))
    with pytest.raises(IngestError, match=rf"{name}\.png: the file name '{name}' read as a time"):
        _ingest(folder, tmp_path / "o", "s")
    assert not (tmp_path / "o" / "frames.parquet").exists()


def test_inspect_describes_an_image_folder_as_the_readme_says(tmp_path: Path, capsys) -> None:
    """``harness inspect DIR`` on a folder of images (issue 53): count, sizes, how the names read
    as times, their order, span and rate, and the session lines; ``--json`` the same as data."""
    import json

    import cv2

    from harness.cli import main

    folder = tmp_path / "cam0"
    folder.mkdir()
    for i in range(5):
        name = f"{1403715273262142976 + i * 50_000_000}.png"
        cv2.imwrite(str(folder / name), np.full((24, 32, 3), 10 * i, np.uint8))
    assert main(["inspect", str(folder)]) == 0
    out = capsys.readouterr().out
    for want in ("(images)", "32x24 (5)", "integers, times in ns", "20.00", "none (no trajectory)",
                 "[[sessions]]", f'source = "{folder}"'):  # fmt: skip
        assert want in out, want
    assert main(["inspect", str(folder), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["images"], info["sizes"], info["in_order"]) == (5, {"32x24": 5}, True)
    assert info["first"] == "1403715273262142976.png" and info["span_s"] == 0.2
    (folder / "notes.png").write_bytes(b"not an image")
    assert main(["inspect", str(folder)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR:") and "notes.png" in err

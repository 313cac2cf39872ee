"""Any robot's data: a folder of images with a trajectory file in TUM, KITTI or EuRoC format.

The three formats the SLAM field's evaluation tool evo reads, read here with numpy (evo is
GPL-3.0; this project is MIT) following evo's documented conventions:

- **TUM** (``tum``): a text file ``timestamp x y z qx qy qz qw`` (seconds, metres; quaternion
  x, y, z, w, Hamilton, the pose of the camera or body in the world frame), comments ``#``.
  Layout: the trajectory ``groundtruth.txt`` (or ``trajectory.txt``, ``poses.txt``) beside an
  image folder ``rgb/`` or ``images/``. Image times from the file names (``<seconds>.png``) or
  from ``rgb.txt`` (``timestamp filename`` per line, as the TUM RGB-D benchmark writes it).
- **KITTI** (``kitti``): ``poses.txt``, one row-major 3x4 matrix ``[R | t]`` per image (12
  numbers), the left camera's pose in the first camera's frame, camera axes x right, y down,
  z forward (the KITTI camera frame); ``times.txt``, one time in seconds per image; images
  ``image_2/`` (or ``image_0/``, ``images/``) in name order. Poses are turned into a z-up world
  (x forward, y left, z up of the first camera: ``x = z_cam, y = -x_cam, z = -y_cam``) and the
  camera's optical axes into body axes (x forward), so yaw is the heading of the optical axis.
- **EuRoC** (``euroc``): ``mav0/state_groundtruth_estimate0/data.csv`` (``timestamp`` in ns,
  ``p_RS_R_x y z`` metres, ``q_RS_w x y z``: the quaternion's **w first**), images
  ``mav0/cam0/data/<ns>.png`` with ``mav0/cam0/data.csv`` (``timestamp, filename``); the pose is
  the body's (the IMU's), as evo reads it.

Each folder is streamed as a log of two topics, compressed images (the files' bytes, never
re-encoded) and ``geometry_msgs/PoseStamped`` poses, so the images, pose interpolation at image
times, the gap rule and the drop counts are the other ingesters' own.
"""

from __future__ import annotations

import decimal
import itertools
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import IngestError
from harness.inputs import IMAGE_SUFFIXES

IMAGE_TOPIC = "/camera/image/compressed"
POSE_TOPIC = "/pose"
Raw = tuple[str, str, int, Any]  # (topic, type, log time ns, message)


def seconds_to_ns(text: str, where: str) -> int:
    """A time in seconds, written as text (``1305031102.175304``, ``6.0e-01``), as exact ns."""
    try:
        return int((decimal.Decimal(text.strip()) * 1_000_000_000).to_integral_value())
    except decimal.InvalidOperation:
        raise ValueError(f"{where}: {text.strip()!r} is not a time in seconds") from None


#: An integer file name's unit by its size (a time since the Unix epoch): at least 1e17 is in ns
#: (EuRoC's ``1403715273262142976``), 1e14 us, 1e11 ms, else seconds.
INTEGER_UNITS = ((10**17, 1), (10**14, 1_000), (10**11, 1_000_000), (0, 1_000_000_000))
#: The largest time a frame can have: int64 nanoseconds.
MAX_NS = 2**63 - 1


def stem_to_ns(stem: str, where: str) -> int:
    """A file name's time in ns, or a ValueError past int64 nanoseconds.

    A decimal number is seconds (TUM); an integer is in ns, us, ms or s by its size
    (:data:`INTEGER_UNITS`).
    """
    text = stem.strip()
    if text.isdigit():
        v = int(text)
        ns = v * next(f for lo, f in INTEGER_UNITS if v >= lo)
    else:
        ns = seconds_to_ns(text, where)
    if not 0 <= ns <= MAX_NS:
        raise ValueError(
            f"{where}: the file name {text!r} read as a time is {ns} ns, outside 0 to 2^63 - 1 "
            "ns; name the files by time in ns, us, ms or s, or list their times in times.txt"
        )
    return ns


def _images_in(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _first(path: Path, names: tuple[str, ...]) -> Path | None:
    return next((path / n for n in names if (path / n).exists()), None)


def _rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number as an editor counts it, fields) of each row of a text file.

    Fields are separated by whitespace or commas; comments (#) and blank lines are skipped.
    """
    out = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if line:
            out.append((n, line.replace(",", " ").split()))
    return out


def _numbers(fields: list[str], where: str) -> np.ndarray:
    """``fields`` as finite float64 numbers, or a ValueError naming ``where`` and the field."""
    try:
        v = np.array([float(x) for x in fields], np.float64)
    except ValueError:
        bad = next(x for x in fields if not _is_float(x))
        raise ValueError(f"{where}: {bad!r} is not a number") from None
    if not np.isfinite(v).all():
        raise ValueError(f"{where}: {fields[int(np.argmin(np.isfinite(v)))]!r} is not finite")
    return v


def _is_float(x: str) -> bool:
    try:
        float(x)
    except ValueError:
        return False
    return True


def _ns(text: str, where: str) -> int:
    """An integer time in nanoseconds (EuRoC), or a ValueError naming ``where``."""
    if not text.isdigit():
        raise ValueError(f"{where}: {text!r} is not a time in integer nanoseconds")
    return int(text)


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a rotation matrix (Shepperd's method, w >= 0)."""
    t = np.trace(r)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    qa = np.asarray(q, np.float64)
    return qa if qa[3] >= 0 else -qa


#: KITTI camera axes (x right, y down, z forward) in the z-up world (x forward, y left, z up).
KITTI_TO_WORLD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def kitti_pose(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), quaternion x, y, z, w) in the z-up world of a KITTI 3x4 camera pose.

    World: ``C @ p``; orientation: ``C @ R @ C.T`` (the camera's body axes, x along the optical
    axis), with ``C`` = :data:`KITTI_TO_WORLD`.
    """
    c = KITTI_TO_WORLD
    return c @ m[:, 3], quat_from_matrix(c @ m[:, :3] @ c.T)


class _Folder:
    """Shared streaming of (image, pose) records of one folder format."""

    name = ""

    def detect(self, path: Path) -> bool:  # pragma: no cover - overridden
        raise NotImplementedError

    def images(self, path: Path) -> list[tuple[int, Path]]:  # pragma: no cover - overridden
        raise NotImplementedError

    def poses(self, path: Path) -> list[tuple[int, np.ndarray, np.ndarray]]:  # pragma: no cover
        raise NotImplementedError

    def topics(self, path: Path) -> dict[str, tuple[str, int]]:
        """Whether ``path`` is a folder of this format."""
        return {
            IMAGE_TOPIC: ("sensor_msgs/msg/CompressedImage", len(self.images(path))),
            POSE_TOPIC: ("geometry_msgs/msg/PoseStamped", len(self.poses(path))),
        }

    def raw(self, path: Path, topics: tuple[str, ...]) -> Iterator[Raw]:
        """Messages of ``topics`` in time order (poses before images of the same time)."""
        from rosbags.typesys import Stores, get_typestore

        ts = get_typestore(Stores.ROS2_HUMBLE)
        T = ts.types
        Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
        recs: list[tuple[int, int, Any]] = []
        if POSE_TOPIC in topics:
            recs += [(t, 0, (p, q)) for t, p, q in self.poses(path)]
        if IMAGE_TOPIC in topics:
            recs += [(t, 1, f) for t, f in self.images(path)]
        recs.sort(key=lambda r: (r[0], r[1]))
        for t, kind, item in recs:
            header = Header(stamp=Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000),
                            frame_id="world" if kind == 0 else "camera")  # fmt: skip
            if kind == 0:
                p, q = item
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                )
                msg = T["geometry_msgs/msg/PoseStamped"](header=header, pose=pose)
                yield POSE_TOPIC, "geometry_msgs/msg/PoseStamped", t, msg
            else:
                data = np.frombuffer(Path(item).read_bytes(), np.uint8)
                fmt = Path(item).suffix.lower().lstrip(".").replace("jpg", "jpeg")
                msg = T["sensor_msgs/msg/CompressedImage"](header=header, format=fmt, data=data)
                yield IMAGE_TOPIC, "sensor_msgs/msg/CompressedImage", t, msg


class TumFolder(_Folder):
    """A TUM trajectory beside an image folder (see the module docstring)."""

    name = "tum"
    TRAJ = ("groundtruth.txt", "trajectory.txt", "poses.txt")
    DIRS = ("rgb", "images")

    def detect(self, path: Path) -> bool:
        """Whether ``path`` is a folder of this format."""
        return path.is_dir() and _first(path, self.TRAJ) is not None and any(
            (path / d).is_dir() for d in self.DIRS
        ) and not (path / "times.txt").exists()  # fmt: skip

    def images(self, path: Path) -> list[tuple[int, Path]]:
        """(time ns, image file) of every image, in time order."""
        d = _first(path, self.DIRS)
        if d is None:
            raise ValueError(f"{path}: no image folder ({' or '.join(self.DIRS)}/)")
        listing = path / "rgb.txt"
        if listing.exists():
            return [
                (seconds_to_ns(r[0], f"{listing}: line {n}"), path / r[1])
                for n, r in _rows(listing)
            ]
        return [(seconds_to_ns(f.stem, f"{f}"), f) for f in _images_in(d)]

    def poses(self, path: Path) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(time ns, position (3,), quaternion x, y, z, w) of every pose."""
        f = _first(path, self.TRAJ)
        if f is None:
            raise IngestError(f"{path}: no trajectory file ({', '.join(self.TRAJ)})")
        out = []
        for i, r in _rows(f):
            if len(r) != 8:
                raise ValueError(
                    f"{f}: line {i}: {len(r)} fields; TUM is 'timestamp x y z qx qy qz qw'"
                )
            v = _numbers(r[1:], f"{f}: line {i}")
            out.append((seconds_to_ns(r[0], f"{f}: line {i}"), v[:3], v[3:]))
        return out


class KittiFolder(_Folder):
    """KITTI odometry poses and times beside an image folder (see the module docstring)."""

    name = "kitti"
    DIRS = ("image_2", "image_0", "images")

    def detect(self, path: Path) -> bool:
        """Whether ``path`` is a folder of this format."""
        return path.is_dir() and (path / "times.txt").exists() and (path / "poses.txt").exists()

    def _times(self, path: Path) -> list[int]:
        f = path / "times.txt"
        return [seconds_to_ns(r[0], f"{f}: line {i}") for i, r in _rows(f)]

    def images(self, path: Path) -> list[tuple[int, Path]]:
        """(time ns, image file) of every image, in time order."""
        d = _first(path, self.DIRS)
        if d is None:
            raise ValueError(f"{path}: no image folder ({' or '.join(self.DIRS)}/)")
        files, times = _images_in(d), self._times(path)
        if len(files) != len(times):
            raise ValueError(
                f"{path}: {len(files)} images in {d.name}/ but {len(times)} lines in times.txt"
            )
        return list(zip(times, files, strict=True))

    def poses(self, path: Path) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(time ns, position (3,), quaternion x, y, z, w) of every pose."""
        f, times = path / "poses.txt", self._times(path)
        rows = _rows(f)
        if len(rows) != len(times):
            raise ValueError(f"{f}: {len(rows)} poses but {len(times)} lines in times.txt")
        out = []
        for t, (i, r) in zip(times, rows, strict=True):
            if len(r) != 12:
                raise ValueError(f"{f}: line {i}: {len(r)} numbers; KITTI is a 3x4 matrix (12)")
            p, q = kitti_pose(_numbers(r, f"{f}: line {i}").reshape(3, 4))
            out.append((t, p, q))
        return out


class EurocFolder(_Folder):
    """An EuRoC MAV sequence (``mav0/``) (see the module docstring)."""

    name = "euroc"

    @staticmethod
    def _root(path: Path) -> Path:
        return path / "mav0" if (path / "mav0").is_dir() else path

    def detect(self, path: Path) -> bool:
        """Whether ``path`` is a folder of this format."""
        return (
            path.is_dir()
            and (self._root(path) / "state_groundtruth_estimate0" / "data.csv").exists()
        )

    def images(self, path: Path) -> list[tuple[int, Path]]:
        """(time ns, image file) of every image, in time order."""
        cam = self._root(path) / "cam0"
        listing = cam / "data.csv"
        if listing.exists():
            return [
                (_ns(r[0], f"{listing}: line {n}"), cam / "data" / r[1]) for n, r in _rows(listing)
            ]
        return [(int(f.stem), f) for f in _images_in(cam / "data")]

    def poses(self, path: Path) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(time ns, position (3,), quaternion x, y, z, w) of every pose."""
        f = self._root(path) / "state_groundtruth_estimate0" / "data.csv"
        out = []
        for i, r in _rows(f):
            if len(r) < 8:
                raise ValueError(f"{f}: line {i}: {len(r)} fields; EuRoC needs at least 8")
            v = _numbers(r[1:8], f"{f}: line {i}")
            out.append((_ns(r[0], f"{f}: line {i}"), v[:3], np.array([v[4], v[5], v[6], v[3]])))
        return out


class ImagesFolder(_Folder):
    """A folder of images and nothing else: no trajectory (method §13.2, ``[pairs] by``).

    The images lie in the folder itself, in file-name order. Their times: ``times.txt`` (one time
    in seconds per image, in name order, as KITTI writes it) if present; else the file names where
    every one is a number: decimal seconds (``1305031102.175304.png``, as TUM names them) or an
    integer in ns, us, ms or s by its size (``1403715273262142976.png``, as EuRoC names them;
    :func:`stem_to_ns`); else one second apart from 0. Asked after the formats with a
    trajectory, so a TUM, KITTI or EuRoC folder is never taken for images alone.
    """

    name = "images"

    def detect(self, path: Path) -> bool:
        """A directory with image files in it (not in a subfolder)."""
        return path.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir())

    def images(self, path: Path) -> list[tuple[int, Path]]:
        """(time ns, image file) of every image, in name order."""
        files = _images_in(path)
        listing = path / "times.txt"
        if listing.exists():
            times = [seconds_to_ns(r[0], f"{listing}: line {i}") for i, r in _rows(listing)]
            if len(times) != len(files):
                raise ValueError(f"{path}: {len(files)} images but {len(times)} lines in times.txt")
        elif files and all(_is_float(f.stem) for f in files):
            times = [stem_to_ns(f.stem, str(f)) for f in files]
        else:
            times = [i * 1_000_000_000 for i in range(len(files))]
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError(f"{path}: image times must increase in file-name order")
        return list(zip(times, files, strict=True))

    def poses(self, path: Path) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """None: the folder has no trajectory."""
        return []

    def topics(self, path: Path) -> dict[str, tuple[str, int]]:
        """The image topic alone."""
        return {IMAGE_TOPIC: ("sensor_msgs/msg/CompressedImage", len(self.images(path)))}


FOLDER_FORMATS: dict[str, _Folder] = {
    r.name: r for r in (TumFolder(), KittiFolder(), EurocFolder(), ImagesFolder())
}


def frame_names(path: Path, fmt: str) -> dict[int, str]:
    """Each image's name by its frame time (utime, µs): its path relative to the session folder.

    The names method §13.2 keeps through every output and pairs by (``[pairs] by = "name"``). The
    times are the ones the ingester gives the frames (:meth:`_Folder.images`, in µs as the frame
    table counts them); an image whose µs repeats an earlier one's is the ingester's duplicate
    and keeps the first name.
    """
    root = Path(path)
    out: dict[int, str] = {}
    for ns, f in FOLDER_FORMATS[fmt].images(root):
        rel = Path(f).relative_to(root) if Path(f).is_relative_to(root) else Path(f)
        out.setdefault(ns // 1000, rel.as_posix())
    return out

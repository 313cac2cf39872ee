"""Pose extraction from messages and interpolation at image times (method §3)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.errors import IngestError

POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "tf2_msgs/msg/TFMessage",
)


#: A quaternion whose norm is within this of 1 is normalised (and counted); beyond it, rejected.
QUAT_TOLERANCE = 1e-3


def euler_from_quaternion(
    x: float,
    y: float,
    z: float,
    w: float,
    where: str = "quaternion",
    stats: dict[str, int] | None = None,
) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) of a unit quaternion, radians.

    A non-finite quaternion gives NaN angles (the pose is then dropped and counted). A norm
    within :data:`QUAT_TOLERANCE` of 1 is normalised (counted in ``stats`` as
    ``quaternion_normalised`` when off by more than 1e-6).

    Raises:
        IngestError: The norm is further from 1 (e.g. Euler angles stored in quaternion fields);
            ``where`` names the file and message.
    """
    if not all(math.isfinite(v) for v in (x, y, z, w)):
        return math.nan, math.nan, math.nan
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(n - 1.0) > QUAT_TOLERANCE:
        raise IngestError(
            f"{where}: orientation quaternion ({x:.6g}, {y:.6g}, {z:.6g}, {w:.6g}) has norm "
            f"{n:.6g}, not 1 "
            f"(tolerance {QUAT_TOLERANCE}); is it Euler angles stored in quaternion fields?"
        )
    if stats is not None and abs(n - 1.0) > 1e-6:
        stats["quaternion_normalised"] = stats.get("quaternion_normalised", 0) + 1
    x, y, z, w = x / n, y / n, z / n, w / n
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    sp = max(-1.0, min(1.0, 2 * (w * y - z * x)))
    pitch = math.asin(sp)
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def stamp_us(header: Any) -> int:
    """A ROS header's stamp in µs."""
    st = header.stamp
    return int(st.sec) * 1_000_000 + int(st.nanosec) // 1000


def _pose_row(
    t: int, pose: Any, where: str, stats: dict[str, int] | None
) -> tuple[int, float, float, float, float, float, float]:
    p, q = pose.position, pose.orientation
    r, pi, y = euler_from_quaternion(q.x, q.y, q.z, q.w, where, stats)
    return (t, float(p.x), float(p.y), float(p.z), r, pi, y)


def pose_rows(
    msg: Any,
    msgtype: str,
    log_us: int,
    time_source: str,
    tf_child: str | None,
    where: str = "pose message",
    stats: dict[str, int] | None = None,
) -> list[tuple]:
    """Pose rows ``(utime, x, y, z, roll, pitch, yaw)`` of one message (µs, metres, radians)."""
    if msgtype == "tf2_msgs/msg/TFMessage":
        out = []
        for tr in msg.transforms:
            if tf_child is not None and tr.child_frame_id != tf_child:
                continue
            t = stamp_us(tr.header) if time_source == "header" else log_us
            tl, q = tr.transform.translation, tr.transform.rotation
            r, pi, y = euler_from_quaternion(
                q.x, q.y, q.z, q.w, f"{where} ({tr.child_frame_id})", stats
            )
            out.append((t, float(tl.x), float(tl.y), float(tl.z), r, pi, y))
        return out
    t = stamp_us(msg.header) if time_source == "header" else log_us
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return [_pose_row(t, msg.pose, where, stats)]
    # Odometry, PoseWithCovarianceStamped
    return [_pose_row(t, msg.pose.pose, where, stats)]


def wrap(a: np.ndarray) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass
class InterpResult:
    """Poses interpolated at the image times, with what was kept and why the rest was not."""

    poses: np.ndarray  # (n, 6) for kept images
    keep: np.ndarray  # (n_images,) bool
    dropped: dict[str, int] = field(default_factory=dict)


def interpolate(
    pose_t: np.ndarray, pose_v: np.ndarray, img_t: np.ndarray, max_gap_us: int
) -> InterpResult:
    """Poses at image times: linear in position, shortest arc in each angle.

    An image keeps its frame only when a pose lies at most ``max_gap_us`` before it and at most
    ``max_gap_us`` after it (an exact match counts as both). The others are dropped and counted
    by reason: ``before_first_pose``, ``after_last_pose``, ``pose_gap``.

    Args:
        pose_t: (m,) strictly increasing pose times, µs.
        pose_v: (m, 6) x, y, z, roll, pitch, yaw.
        img_t: (n,) image times, µs.
        max_gap_us: largest allowed distance to the pose on each side.
    """
    n = len(img_t)
    dropped = {"before_first_pose": 0, "after_last_pose": 0, "pose_gap": 0}
    if len(pose_t) == 0:
        dropped["before_first_pose"] = n
        return InterpResult(np.zeros((0, 6)), np.zeros(n, bool), dropped)
    j = np.searchsorted(pose_t, img_t, side="right")  # pose_t[j-1] <= t < pose_t[j]
    lo = np.clip(j - 1, 0, len(pose_t) - 1)
    hi = np.clip(j, 0, len(pose_t) - 1)
    exact = pose_t[lo] == img_t
    hi = np.where(exact, lo, hi)
    before = j == 0
    after = (j >= len(pose_t)) & ~exact
    gap = ~before & ~after & ((img_t - pose_t[lo] > max_gap_us) | (pose_t[hi] - img_t > max_gap_us))
    keep = ~before & ~after & ~gap
    dropped["before_first_pose"] = int(before.sum())
    dropped["after_last_pose"] = int(after.sum())
    dropped["pose_gap"] = int(gap.sum())
    lo, hi, t = lo[keep], hi[keep], img_t[keep]
    span = (pose_t[hi] - pose_t[lo]).astype(np.float64)
    w = np.where(span > 0, (t - pose_t[lo]) / np.where(span > 0, span, 1), 0.0)[:, None]
    a, b = pose_v[lo], pose_v[hi]
    out = np.empty_like(a)
    out[:, :3] = a[:, :3] + w * (b[:, :3] - a[:, :3])
    out[:, 3:] = wrap(a[:, 3:] + w * wrap(b[:, 3:] - a[:, 3:]))
    # an exact match returns the pose itself, bit for bit
    ex = w[:, 0] == 0
    out[ex] = a[ex]
    return InterpResult(out, keep, dropped)


def check_monotonic(
    t: np.ndarray, where: str, what: str, numbers: np.ndarray | None = None, unit: str = "message"
) -> None:
    """Raise if time stamps go backwards (equal stamps are allowed here and handled by the caller).

    Args:
        t: (n,) time stamps, µs.
        where: the log (or file) named in the error.
        what: which stamps (``image``, ``pose``, ``ground-truth``).
        numbers: the 1-based message or line number of each stamp (default 1..n), named in the
            error.
        unit: what ``numbers`` count (``message``, ``line``).
    """
    if len(t) > 1:
        back = np.nonzero(np.diff(t) < 0)[0]
        if len(back):
            i = int(back[0])
            num = np.arange(1, len(t) + 1) if numbers is None else np.asarray(numbers)
            raise IngestError(
                f"{where}: {what} time stamps are not monotonic: {unit} {int(num[i + 1])} "
                f"at utime {int(t[i + 1])} "
                f"comes after {unit} {int(num[i])} at utime {int(t[i])} ({len(back)} "
                "backward step(s) in all)"
            )

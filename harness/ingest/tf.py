"""Camera poses from a ``/tf`` tree (method §3).

The pose of a target frame (the camera) in a fixed frame, composed through every transform on the
path at each image time.

Dynamic transforms (``/tf``) are interpolated at the image time, linear in translation and by
slerp in rotation, and only between two samples each at most that transform's gap away (the
same rule as for pose topics); static transforms (``/tf_static``) are taken as they are. A frame
whose path breaks, or whose path holds a transform outside its gap, is dropped and counted under
that transform's name (``parent->child``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from harness.errors import IngestError


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (n, 4) quaternions in (x, y, z, w) order."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate (n, 3) vectors by (n, 4) unit quaternions (x, y, z, w)."""
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation of (n, 4) unit quaternions at fractions (n,), shortest arc."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-9
    s = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / s)
    w1 = np.where(small, t, np.sin(t * theta) / s)
    out = w0[:, None] * q0 + w1[:, None] * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


@dataclass
class Transform:
    """All samples of one edge ``parent -> child`` of the tree (times in µs)."""

    parent: str
    child: str
    static: bool
    times: list[int] = field(default_factory=list)
    trans: list[tuple[float, float, float]] = field(default_factory=list)
    rot: list[tuple[float, float, float, float]] = field(default_factory=list)

    @property
    def name(self) -> str:
        """``parent->child``."""
        return f"{self.parent}->{self.child}"

    def median_interval_s(self) -> float:
        """Median time between the edge's samples, seconds (inf with fewer than two)."""
        t = np.unique(np.asarray(self.times, np.int64))
        return float(np.median(np.diff(t))) / 1e6 if len(t) > 1 else float("inf")


class TfTree:
    """The transforms of a log, keyed by child frame (tf is a tree: one parent per child)."""

    def __init__(self) -> None:
        self.edges: dict[str, Transform] = {}

    def add(
        self,
        parent: str,
        child: str,
        t_us: int,
        trans: tuple[float, float, float],
        rot: tuple[float, float, float, float],
        static: bool,
        where: str,
    ) -> None:
        """Add one transform sample ``parent -> child`` at ``t_us`` (µs; metres, quaternion)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        e = self.edges.get(child)
        if e is None:
            e = self.edges[child] = Transform(parent, child, static)
        elif e.parent != parent:
            raise IngestError(
                f"{where}: frame {child!r} has two parents in /tf ({e.parent!r} and "
                f"{parent!r}); a tf tree allows one"
            )
        e.static = e.static and static
        e.times.append(int(t_us))
        e.trans.append(trans)
        e.rot.append(rot)

    def touch(self, parent: str, child: str, static: bool, where: str) -> None:
        """Record the edge ``parent -> child`` without a sample (its only samples were not finite).

        The tree keeps its shape: a transform whose values are all NaN still links its frames,
        so the root stays where it is and the frames it fails are dropped and counted under it.
        """
        parent, child = parent.lstrip("/"), child.lstrip("/")
        e = self.edges.get(child)
        if e is None:
            self.edges[child] = Transform(parent, child, static)
        elif e.parent != parent:
            raise IngestError(
                f"{where}: frame {child!r} has two parents in /tf ({e.parent!r} and "
                f"{parent!r}); a tf tree allows one"
            )

    def frames(self) -> set[str]:
        """Every frame named in the tree."""
        return set(self.edges) | {e.parent for e in self.edges.values()}

    def roots(self) -> list[str]:
        """Frames that are nobody's child, sorted."""
        return sorted({e.parent for e in self.edges.values()} - set(self.edges))

    def path(self, fixed: str, target: str) -> list[Transform]:
        """The edges from ``fixed`` down to ``target`` (empty when they are the same frame).

        Raises:
            IngestError: ``target`` is not below ``fixed``; names where the chain stops.
        """
        chain: list[Transform] = []
        f = target
        seen = set()
        while f != fixed:
            if f in seen:
                raise IngestError(f"/tf has a cycle through {f!r}")
            seen.add(f)
            e = self.edges.get(f)
            if e is None:
                up = " -> ".join(reversed([target, *[c.parent for c in chain]]))
                raise IngestError(
                    f"/tf: no path from {fixed!r} to {target!r}: the chain up from "
                    f"{target!r} ({up}) ends at {f!r}, "
                    f"which has no parent transform (missing transform: ? -> {f}); roots of "
                    f"the tree: {self.roots()}"
                )
            chain.append(e)
            f = e.parent
        return list(reversed(chain))

    def lookup(
        self, fixed: str, target: str, t_us: np.ndarray, gap_us: dict[str, int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, dict[str, int]]]:
        """Pose of ``target`` in ``fixed`` at times ``t_us``.

        Args:
            fixed: the frame the pose is expressed in (the tree's root or ``fixed_frame``).
            target: the frame whose pose is wanted (the camera's).
            t_us: (n,) the image times, µs.
            gap_us: the largest allowed gap per dynamic transform (by ``parent->child``).

        Returns:
            (translation (n, 3), rotation (n, 4) x, y, z, w, ok (n,) bool, drops per transform and
            reason: ``{"map->odom": {"pose_gap": 3}}``; a frame is counted under the first transform
            of its path that fails).
        """
        n = len(t_us)
        trans = np.zeros((n, 3))
        rot = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        ok = np.ones(n, bool)
        drops: dict[str, dict[str, int]] = {}
        for e in self.path(fixed, target):
            tr, q, good, why = _sample(e, t_us, gap_us.get(e.name, 0))
            for reason, mask in why.items():
                c = int((mask & ok).sum())
                if c:
                    drops.setdefault(e.name, {})[reason] = c
            ok &= good
            # T_fixed_child = T_fixed_parent * T_parent_child
            trans = trans + quat_rotate(rot, tr)
            rot = quat_mul(rot, q)
        return trans, rot / np.linalg.norm(rot, axis=1, keepdims=True), ok, drops


def _sample(
    e: Transform, t_us: np.ndarray, gap: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """One edge at the image times: (translation, rotation, ok, masks of failures by reason)."""
    n = len(t_us)
    if not e.times:  # every sample was non-finite: no image gets a pose through this edge
        return (
            np.zeros((n, 3)),
            np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
            np.zeros(n, bool),
            {"no_finite_sample": np.ones(n, bool)},
        )
    times = np.asarray(e.times, np.int64)
    order = np.argsort(times, kind="stable")
    times = times[order]
    tr = np.asarray(e.trans, np.float64)[order]
    q = np.asarray(e.rot, np.float64)[order]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    if e.static:  # /tf_static: the latest sample holds at every time
        return np.tile(tr[-1], (n, 1)), np.tile(q[-1], (n, 1)), np.ones(n, bool), {}
    j = np.searchsorted(times, t_us, side="right")
    lo = np.clip(j - 1, 0, len(times) - 1)
    hi = np.clip(j, 0, len(times) - 1)
    exact = times[lo] == t_us
    hi = np.where(exact, lo, hi)
    before = j == 0
    after = (j >= len(times)) & ~exact
    gapm = ~before & ~after & ((t_us - times[lo] > gap) | (times[hi] - t_us > gap))
    span = (times[hi] - times[lo]).astype(np.float64)
    w = np.where(span > 0, (t_us - times[lo]) / np.where(span > 0, span, 1), 0.0)
    out_t = tr[lo] + w[:, None] * (tr[hi] - tr[lo])
    out_q = slerp(q[lo], q[hi], w)
    good = ~before & ~after & ~gapm
    return out_t, out_q, good, {"before_first": before, "after_last": after, "pose_gap": gapm}

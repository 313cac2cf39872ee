"""The plain difference of a registered pair: Table D's strongest row that localizes nothing.

docs/decisions.md, *The plain difference*. Two steps, each a share of the frame so that one setting
serves every frame size:

1. **Register** (:func:`register`): SIFT (``[detect.keypoints]``' features and ratio test, both
   ways) and a homography by MAGSAC carry the map frame onto the query frame. A pair is
   *comparable* only with at least ``min_inliers`` inliers, a warp that keeps the frame's
   orientation and scale within ``max_scale`` and a warped map that covers at least
   ``min_footprint`` of the query frame; otherwise it says why (:attr:`Registration.why`) and
   carries no change score.
2. **Compare** (:func:`difference_map`): both frames in CIELAB on a copy whose longer side is at
   most ``side`` pixels, the map's gain and offset matched to the query's over the pixels both
   see; each query pixel's smallest colour distance to the warped map within ``shift`` of the
   frame's diagonal; a Gaussian blur of sigma ``blur`` of the diagonal, normalised by the
   footprint so that pixels the map does not see (NaN) take part in nothing.

A box scores its mean difference over one plus its ring's (``box_score = "ratio"``) or less it
(``"contrast"``): a change differs more than its surroundings. Where ``colour`` is "novelty" the
box's score is that times the same score of the colours' novelty (:mod:`harness.detect.colour`),
each floored at 0 (:func:`box_differences`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from harness.detect.colour import colour_novelty
from harness.detect.config import DifferenceConfig
from harness.localizers.align import align_ecc
from harness.localizers.config import KeypointConfig, LocalConfig
from harness.localizers.keypoints import MapFeatures, stored_keypoints, union_matches

#: What a pair that could not be registered is compared through (``not_comparable =
#: "fallback"``): an affine fit of its intensities, or the frames as they stand.
FALLBACKS = ("ecc", "identity")


@dataclass(frozen=True)
class Registration:
    """A pair's registration: ``H`` maps map-frame pixels to query-frame pixels (full size)."""

    H: np.ndarray | None
    inliers: int
    matches: int
    footprint: float  # the share of the query frame the warped map covers
    why: str  # "" where comparable, else why not
    # "homography"; a fallback's "ecc" (an affine fit of the intensities) or "identity"; "none"
    method: str = "homography"
    # what the homography cannot express (parallax): the median distance of the pair's matched
    # keypoints from where it puts them, a share of the query frame's diagonal
    residual: float = float("nan")

    @property
    def comparable(self) -> bool:
        """Whether the pair was registered (nothing to say why not)."""
        return not self.why

    @property
    def compares(self) -> bool:
        """Whether a difference is read through it: a registration, or a fallback's warp."""
        return self.H is not None and (self.comparable or self.method in FALLBACKS)

    def similarity(self, w: int, h: int) -> tuple[float, float, float, float]:
        """The warp as a perturbed copy of the map frame would draw it.

        The centre's shift (shares of ``w``, ``h``), rotation (degrees) and scale of the
        similarity nearest to the homography at the centre (:class:`harness.perturb.
        Perturbation`'s ``dx``, ``dy``, ``rotation_deg``, ``scale``); NaN where there is none.
        """
        if self.H is None or not self.comparable:
            return (float("nan"),) * 4
        H, (x, y) = self.H, (w / 2.0, h / 2.0)
        den = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / den
        v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / den
        j = np.array([[H[0, 0] - u * H[2, 0], H[0, 1] - u * H[2, 1]],
                      [H[1, 0] - v * H[2, 0], H[1, 1] - v * H[2, 1]]]) / den  # fmt: skip
        a, b = (j[0, 0] + j[1, 1]) / 2.0, (j[0, 1] - j[1, 0]) / 2.0
        return (
            float((u - x) / w),
            float((v - y) / h),
            float(np.degrees(np.arctan2(b, a))),
            float(np.hypot(a, b)),
        )

    def fallback(
        self, q_rgb: np.ndarray, m_rgb: np.ndarray, dc: DifferenceConfig, local: LocalConfig
    ) -> Registration:
        """The pair compared without keypoints: an affine fit of its intensities, or as it stands.

        The fit: OpenCV's ``findTransformECC`` on copies ``fallback_side`` pixels on the longer
        side by the run's ``[detect.local]`` (``local``), accepted with a correlation of at least
        0.6 and a plausible warp. It is no registration: it keeps this one's reason
        (:attr:`comparable` stays False) and is read through :attr:`compares`.

        ``[detect] not_comparable = "fallback"``: its boxes are marked and measured apart.
        """
        q, fq = scaled_copy(to_gray(q_rgb), dc.fallback_side)
        m = cv2.resize(to_gray(m_rgb), (q.shape[1], q.shape[0]), interpolation=cv2.INTER_AREA)
        to_small = np.diag([q.shape[1] / m_rgb.shape[1], q.shape[0] / m_rgb.shape[0], 1.0])
        al = align_ecc(q, m, local)
        method, Hs = "identity", np.eye(3)
        if al is not None and al.H is not None:
            method, Hs = "ecc", np.linalg.inv(al.H)
        full = np.diag([1 / fq, 1 / fq, 1.0]) @ Hs @ to_small
        return Registration(full, 0, self.matches, 1.0, self.why or "not registered", method)


def scaled_copy(rgb: np.ndarray, side: int) -> tuple[np.ndarray, float]:
    """``rgb`` with its longer side at most ``side`` pixels (area interpolation), and the scale."""
    h, w = rgb.shape[:2]
    f = min(1.0, side / float(max(h, w)))
    if f >= 1:
        return rgb, 1.0
    size = (max(1, round(w * f)), max(1, round(h * f)))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), f


def to_gray(rgb: np.ndarray) -> np.ndarray:
    """``rgb`` in grey (a grey frame as it is)."""
    return rgb if rgb.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def warped_footprint(
    H: np.ndarray, m_shape: tuple[int, int], q_shape: tuple[int, int]
) -> np.ndarray:
    """Which query pixels the warped map frame covers (bool, the query's shape)."""
    ones = np.full(m_shape, 255, np.uint8)
    got = cv2.warpPerspective(ones, H, (q_shape[1], q_shape[0]), flags=cv2.INTER_NEAREST)
    return got > 0


def _scale_ok(H: np.ndarray, w: int, h: int, max_scale: float) -> bool:
    """Whether ``H`` keeps orientation and its local scale within the limit over the frame."""
    if not np.all(np.isfinite(H)):
        return False
    pts = np.array([[x, y] for x in (0, w / 2, w) for y in (0, h / 2, h)], np.float64)
    for x, y in pts:
        den = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        if abs(den) < 1e-9:
            return False
        # the Jacobian of the projective map at (x, y)
        u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / den
        v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / den
        jac = np.array(
            [[H[0, 0] - u * H[2, 0], H[0, 1] - u * H[2, 1]],
             [H[1, 0] - v * H[2, 0], H[1, 1] - v * H[2, 1]]]
        ) / den  # fmt: skip
        det = float(np.linalg.det(jac))
        if det <= 0 or not 1 / max_scale**2 <= det <= max_scale**2:
            return False
    return True


def parallax_residual(
    src: np.ndarray, dst: np.ndarray, H: np.ndarray, mask: np.ndarray, thr: float
) -> float:
    """What the homography ``H`` leaves of the pair's motion (parallax), in working pixels.

    The median distance of the matches that agree with the pair's epipolar geometry (a fundamental
    matrix by MAGSAC, so a wrong match does not count) from where ``H`` puts them; over the
    homography's own inliers where no fundamental matrix is found.
    """
    keep = mask.ravel().astype(bool)
    if len(src) >= 8:
        try:
            F, fmask = cv2.findFundamentalMat(src, dst, cv2.USAC_MAGSAC, thr, 0.999, 2000)
        except cv2.error:
            F, fmask = None, None
        if F is not None and fmask is not None and F.shape == (3, 3) and fmask.sum() >= 8:
            keep = fmask.ravel().astype(bool)
    moved = cv2.perspectiveTransform(src[keep].reshape(-1, 1, 2).astype(np.float64), H)
    return float(np.median(np.hypot(*(moved.reshape(-1, 2) - dst[keep]).T)))


def register(
    q_rgb: np.ndarray,
    m_rgb: np.ndarray,
    kc: KeypointConfig,
    dc: DifferenceConfig,
    features: tuple[MapFeatures, str, str] | None = None,
) -> Registration:
    """The map frame registered onto the query frame by a homography (docs/method.md).

    ``features``: a cache of keypoints and the two images' URIs (a frame in several pairs, as a
    shared map frame or the null's query, is detected once); without it, this process's store
    (:func:`harness.localizers.keypoints.stored_keypoints`).
    """
    q, fq = scaled_copy(to_gray(q_rgb), dc.register_side)
    m, fm = scaled_copy(to_gray(m_rgb), dc.register_side)
    if features is not None:
        cache, q_uri, m_uri = features
        (xq, dq), (xm, dm) = cache.of(q_uri, q), cache.of(m_uri, m)
    else:
        (xq, dq), (xm, dm) = stored_keypoints(q, kc), stored_keypoints(m, kc)
    both = union_matches(dq, dm, kc)
    if len(both) < max(4, dc.min_inliers):
        return Registration(None, 0, len(both), 0.0, f"too few matches ({len(both)})", "none")
    src = xm[both[:, 1]].astype(np.float32)
    dst = xq[both[:, 0]].astype(np.float32)
    thr = max(0.5, kc.ransac_threshold * float(np.hypot(*q.shape[:2])))
    try:
        H, mask = cv2.findHomography(
            src, dst, cv2.USAC_MAGSAC, thr, maxIters=2000, confidence=0.999
        )
    except cv2.error:
        H, mask = None, None
    if H is None or mask is None:
        return Registration(None, 0, len(both), 0.0, "no homography found", "none")
    n = int(mask.sum())
    residual = parallax_residual(src, dst, H, mask, thr) / float(np.hypot(*q.shape[:2]))
    # back to full-size pixels: map pixels -> work map -> work query -> query pixels
    full = np.diag([1 / fq, 1 / fq, 1.0]) @ H @ np.diag([fm, fm, 1.0])
    hq, wq = q_rgb.shape[:2]
    foot = float(warped_footprint(full, m_rgb.shape[:2], (hq, wq)).mean())
    if n < dc.min_inliers:
        why = f"too few inliers ({n} < {dc.min_inliers})"
    elif not _scale_ok(full, wq, hq, dc.max_scale):
        why = "a degenerate warp (flipped, or scaled beyond max_scale)"
    elif foot < dc.min_footprint:
        why = f"the warped map covers {foot:.0%} of the frame (< {dc.min_footprint:.0%})"
    else:
        why = ""
    return Registration(full, n, len(both), foot, why, residual=round(residual, 6))


def _lab(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb, np.uint8), cv2.COLOR_RGB2Lab).astype(np.float32)


def _least_squared_distance(ql: np.ndarray, ml: np.ndarray, r: int) -> np.ndarray:
    """Each pixel's least squared Lab distance to ``ml`` shifted up to ``r`` pixels either way.

    Edges repeated; the root is taken once, after. Channel planes, contiguous, buffers reused: the
    sum runs L, a, b in that order, as a per-pixel sum over the channel axis does (the same
    float32 values), by OpenCV's elementwise calls (IEEE float32 operations: numpy's bits, in half
    numpy's time).
    """
    h, w = ql.shape[:2]
    q = [np.ascontiguousarray(ql[..., c]) for c in range(3)]
    pad = [
        cv2.copyMakeBorder(np.ascontiguousarray(ml[..., c]), r, r, r, r, cv2.BORDER_REPLICATE)
        for c in range(3)
    ]
    best = np.full((h, w), np.inf, np.float32)
    acc, d = np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            for c in range(3):
                cv2.subtract(q[c], pad[c][r + dy : r + dy + h, r + dx : r + dx + w], dst=d)
                if c == 0:
                    cv2.multiply(d, d, dst=acc)
                else:
                    cv2.multiply(d, d, dst=d)
                    cv2.add(acc, d, dst=acc)
            cv2.min(best, acc, dst=best)
    return best


def _mean_std(lab: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``lab[sel].mean(0)`` and ``lab[sel].std(0)``, bit for bit, a channel at a time.

    numpy's own steps (``numpy._core._methods``): the float32 sum over the pixels divided by
    their count, then the mean of the squared deviations, its square root. numpy sums the rows of
    ``lab[sel]`` one after another (a reduction over the outer axis), so each channel's sum is a
    running float32 sum in pixel order: ``np.add.accumulate`` of the channel's gathered pixels
    ends on the same value, in 0.6x the time of the reduction over (pixels, 3) (8.3 ms against
    13.7 ms on a 640 x 480 frame, measured).
    """
    k = lab.shape[-1]
    flat = bool(sel.all())
    n = np.intp(sel.size if flat else np.count_nonzero(sel))
    mean, var = np.zeros((1, k), np.float32), np.zeros(k, np.float32)
    planes = [lab[..., c].reshape(-1) if flat else lab[..., c][sel] for c in range(k)]
    for c, x in enumerate(planes):
        if len(x):
            mean[0, c] = np.add.accumulate(x)[-1]
    np.true_divide(mean, n, out=mean, casting="unsafe")
    for c, x in enumerate(planes):
        dev = np.subtract(x, mean[0, c])
        np.multiply(dev, dev, out=dev)
        if len(dev):
            var[c] = np.add.accumulate(dev, out=dev)[-1]
    np.true_divide(var, n, out=var, casting="unsafe")
    return mean[0], np.sqrt(var, out=var)


def difference_map(
    q_rgb: np.ndarray, m_rgb: np.ndarray, reg: Registration, dc: DifferenceConfig
) -> tuple[np.ndarray, float] | None:
    """The registered pair's difference on the query's working copy, and that copy's scale.

    NaN where the warped map does not reach; None where nothing compares the pair (it was not
    registered and no fallback warp was given, :attr:`Registration.compares`).
    """
    if not reg.compares or reg.H is None:
        return None
    q, f = scaled_copy(q_rgb, dc.side)
    h, w = q.shape[:2]
    H = np.diag([f, f, 1.0]) @ reg.H  # map pixels -> the query's working copy
    mw = cv2.warpPerspective(
        np.ascontiguousarray(m_rgb, np.uint8), H, (w, h), flags=cv2.INTER_AREA
        if f < 1 else cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip
    foot = warped_footprint(H, m_rgb.shape[:2], (h, w))
    ql, ml = _lab(q), _lab(mw)
    sel = foot if foot.any() else np.ones_like(foot)
    qm, qs = _mean_std(ql, sel)
    mm, ms = _mean_std(ml, sel)
    qs, ms = qs + 1e-6, ms + 1e-6
    np.subtract(ml, mm, out=ml)  # the map's colours onto the query's: (ml - mm) * (qs / ms) + qm,
    np.multiply(ml, qs / ms, out=ml)  # in place (the same float32 operations, the same values)
    np.add(ml, qm, out=ml)
    diag = float(np.hypot(h, w))
    best = _least_squared_distance(ql, ml, max(0, round(dc.shift * diag)))
    np.sqrt(best, out=best)
    best[~foot] = 0.0
    sigma = dc.blur * diag
    if sigma > 0:
        wts = cv2.GaussianBlur(foot.astype(np.float32), (0, 0), sigma)
        best = (cv2.GaussianBlur(best, (0, 0), sigma) / np.maximum(wts, 1e-6)).astype(np.float32)
    best[~foot] = np.nan
    return best.astype(np.float32), f


def difference_contrast(
    dmap: np.ndarray, scale: float, boxes: np.ndarray, dc: DifferenceConfig | None = None
) -> np.ndarray:
    """Each box's (frame pixels) score on ``dmap`` (its ``scale``) by ``dc``'s box score.

    ``contrast``: the mean difference inside less the mean of its ring (the box grown by
    ``dc.ring`` of its size on each side, clipped to the frame; pixels the map does not reach
    left out); ``ratio``: the mean inside over one plus the ring's. NaN where the box holds no
    compared pixel.
    """
    dc = dc or DifferenceConfig()
    b = np.asarray(boxes, np.float64).reshape(-1, 4) * scale
    ok = np.isfinite(dmap)
    val = cv2.integral(np.where(ok, dmap, 0).astype(np.float64))
    cnt = cv2.integral(ok.astype(np.uint8)).astype(np.float64)
    h, w = dmap.shape

    def sums(x1: np.ndarray, y1: np.ndarray, x2: np.ndarray, y2: np.ndarray) -> tuple:
        # the pixels whose centres lie in each box, as boxes.inside_score reads them; every box
        # at once, each sum in the order one box's was taken (the same float64 values)
        u0, u1 = np.maximum(np.ceil(x1 - 0.5), 0), np.minimum(np.ceil(x2 - 0.5), w)
        v0, v1 = np.maximum(np.ceil(y1 - 0.5), 0), np.minimum(np.ceil(y2 - 0.5), h)
        empty = (u1 <= u0) | (v1 <= v0)
        a, c = np.clip(u0, 0, w).astype(np.intp), np.clip(u1, 0, w).astype(np.intp)
        b, d = np.clip(v0, 0, h).astype(np.intp), np.clip(v1, 0, h).astype(np.intp)
        s = val[d, c] - val[b, c] - val[d, a] + val[b, a]
        n = cnt[d, c] - cnt[b, c] - cnt[d, a] + cnt[b, a]
        return np.where(empty, 0.0, s), np.where(empty, 0.0, n)

    x1, y1, x2, y2 = b.T
    si, ni = sums(x1, y1, x2, y2)
    gw, gh = (x2 - x1) * dc.ring, (y2 - y1) * dc.ring
    so, no = sums(x1 - gw, y1 - gh, x2 + gw, y2 + gh)
    out = np.full(len(b), np.nan)
    held = ni > 0  # boxes holding a compared pixel
    si, ni, so, no = si[held], ni[held], so[held], no[held]
    inner = si / ni
    apart = no > ni
    ring = np.zeros(len(inner))
    ring[apart] = (so[apart] - si[apart]) / (no[apart] - ni[apart])
    out[held] = inner - ring if dc.box_score == "contrast" else inner / (1.0 + ring)
    return out


def box_differences(
    made: tuple[np.ndarray, float] | None,
    novelty: tuple[np.ndarray, float] | None,
    boxes: np.ndarray,
    dc: DifferenceConfig,
) -> np.ndarray:
    """Each box's plain-difference score: its difference (``made``), times its colours' novelty.

    Where ``dc.colour`` is "novelty" (``novelty`` given) both are floored at 0 and multiplied; NaN
    where the pair was compared by nothing.
    """
    if made is None:
        return np.full(len(boxes), np.nan)
    d = difference_contrast(*made, boxes, dc)
    if novelty is None:
        return d
    return np.maximum(d, 0.0) * np.maximum(difference_contrast(*novelty, boxes, dc), 0.0)


def novelty_of(q_rgb: np.ndarray, m_rgb: np.ndarray, dc: DifferenceConfig) -> Any:
    """The pair's colour novelty where ``dc.colour`` asks for it, else None."""
    return colour_novelty(q_rgb, m_rgb, dc) if dc.colour == "novelty" else None

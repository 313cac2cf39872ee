"""The local localizer's alignment of a pair (method §13.3): the map frame warped onto the query's.

:func:`align_pair` tries the chain of ``[detect.local] align`` in order: a homography from ORB
(or SIFT) matches with RANSAC, accepted only with enough inliers and a plausible warp; an affine
ECC fit (``cv2.findTransformECC``); identity where the two frames still overlap. A warp is kept
only where it fits the pair's gradient images (:func:`feature_image`) better than identity does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from harness.features import extractor, norm_of, ratio_matches
from harness.localizers.config import LocalConfig

__all__ = ["Alignment", "align_pair", "feature_image"]


@dataclass(frozen=True)
class Alignment:
    """How a pair was aligned: ``H`` maps query pixels to map pixels (None: not aligned)."""

    method: str  # homography, ecc, identity or "none"
    inliers: int
    score: float  # the homography's inlier share, ECC's correlation, identity's NCC
    H: np.ndarray | None


def _plausible(H: np.ndarray, w: int, h: int, max_shift: float) -> bool:
    """Whether ``H`` moves no corner of a ``w`` x ``h`` frame over ``max_shift`` of its diagonal."""
    if not np.all(np.isfinite(H)) or abs(float(np.linalg.det(H[:2, :2]))) < 1e-6:
        return False
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64).reshape(-1, 1, 2)
    moved = cv2.perspectiveTransform(corners, H).reshape(-1, 2)
    shift = np.hypot(*(moved - corners.reshape(-1, 2)).T)
    return bool(shift.max() <= max_shift * math.hypot(w, h))


#: The homography's ratio test (one way): stricter than keypoint localization's 0.8, since a
#: wrong match here misplaces every box of the pair.
ALIGN_RATIO = 0.75


def _homography(q: np.ndarray, m: np.ndarray, lc: LocalConfig) -> Alignment | None:
    det = extractor(lc.keypoints, lc.max_keypoints)
    kq, dq = det.detectAndCompute(q, None)
    km, dm = det.detectAndCompute(m, None)
    if dq is None or dm is None or len(kq) < lc.min_inliers or len(km) < lc.min_inliers:
        return None
    good = ratio_matches(dq, dm, ALIGN_RATIO, norm_of(lc.keypoints))  # one way
    if len(good) < lc.min_inliers:
        return None
    src = np.array([kq[i].pt for i in good[:, 0]], np.float32).reshape(-1, 1, 2)
    dst = np.array([km[j].pt for j in good[:, 1]], np.float32).reshape(-1, 1, 2)
    H, mask = cv2.findHomography(src, dst, cv2.RANSAC, 3.0, maxIters=2000, confidence=0.995)
    if H is None or mask is None:
        return None
    n = int(mask.sum())
    h, w = q.shape[:2]
    if n < lc.min_inliers or not _plausible(H, w, h, lc.max_corner_shift):
        return None
    return Alignment("homography", n, n / len(good), H)


def _ecc(q: np.ndarray, m: np.ndarray, lc: LocalConfig) -> Alignment | None:
    warp = np.eye(2, 3, dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    try:  # warp maps map (template) pixels to query (input) pixels
        cc, warp = cv2.findTransformECC(  # type: ignore[call-overload]
            m.astype(np.float32), q.astype(np.float32), warp, cv2.MOTION_AFFINE, crit, None, 5
        )
    except cv2.error:
        return None
    W = np.vstack([warp.astype(np.float64), [0.0, 0.0, 1.0]])
    try:
        H = np.linalg.inv(W)
    except np.linalg.LinAlgError:
        return None
    h, w = q.shape[:2]
    if cc < lc.ecc_min_cc or not _plausible(H, w, h, lc.max_corner_shift):
        return None
    return Alignment("ecc", 0, float(cc), H)


def _identity(q: np.ndarray, m: np.ndarray, lc: LocalConfig) -> Alignment | None:
    if q.shape != m.shape:
        return None
    ncc = float(cv2.matchTemplate(q, m, cv2.TM_CCOEFF_NORMED)[0, 0])
    return Alignment("identity", 0, ncc, np.eye(3)) if ncc >= lc.identity_min_ncc else None


_ALIGN = {"homography": _homography, "ecc": _ecc, "identity": _identity}
#: An affine ECC fit of two gray frames of one size (``H`` maps query pixels to map pixels).
align_ecc = _ecc


def _fit(fq: np.ndarray, fm: np.ndarray, H: np.ndarray | None) -> float:
    """NCC of the query's and the warped map's gradient images where the warped map has pixels.

    ``fq``, ``fm``: the gradient images; ``H`` None: identity (no warp).
    """
    if H is None:
        a, b = fq.ravel(), fm.ravel()
    else:
        h, w = fq.shape
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        warped = cv2.warpPerspective(fm, H, (w, h), flags=flags)
        valid = cv2.warpPerspective(np.ones(fq.shape, np.uint8), H, (w, h), flags=flags) > 0
        if valid.mean() < 0.5:
            return -1.0
        a, b = fq[valid], warped[valid]
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else 0.0


def align_pair(q_gray: np.ndarray, m_gray: np.ndarray, lc: LocalConfig) -> Alignment:
    """The first link of ``lc.align`` that accepts the pair (uint8 gray images of one size).

    A warp (homography, ECC) is accepted only where it fits the pair's gradient images better
    than identity does (their NCC over the overlap): a fit that converged to a wrong warp moves
    every box off its place, which is worse than the small parallax it was meant to remove.
    Images longer than ``lc.align_side`` are aligned on a pyramid level no longer than it, and
    the warp is scaled back.
    """
    f = 1
    while max(q_gray.shape) / f > lc.align_side and min(q_gray.shape) / f >= 64:
        f *= 2
    if f > 1:
        q, m = q_gray, m_gray
        for _ in range(f.bit_length() - 1):
            q, m = cv2.pyrDown(q), cv2.pyrDown(m)
        got = _align_at(q, m, lc)
        if got.H is None:
            return got
        S = np.diag([float(f), float(f), 1.0])
        return Alignment(got.method, got.inliers, got.score, S @ got.H @ np.linalg.inv(S))
    return _align_at(q_gray, m_gray, lc)


def _align_at(q_gray: np.ndarray, m_gray: np.ndarray, lc: LocalConfig) -> Alignment:
    """:func:`align_pair` at the images' own size."""
    warps = [a for a in lc.align if a != "identity"]
    fq = feature_image(q_gray, "gradient") if warps else None
    fm = feature_image(m_gray, "gradient") if warps else None
    ident = -1.0
    if fq is not None and fm is not None and q_gray.shape == m_gray.shape:
        ident = _fit(fq, fm, None)
    for name in lc.align:
        got = _ALIGN[name](q_gray, m_gray, lc)
        if got is None:
            continue
        warp = name != "identity" and got.H is not None
        if warp and fq is not None and fm is not None and _fit(fq, fm, got.H) <= ident:
            continue
        return got
    return Alignment("none", 0, float("nan"), None)


def feature_image(gray: np.ndarray, kind: str) -> np.ndarray:
    """The image a subimage is matched on: Sobel gradient magnitude or the gray levels (float32)."""
    g: np.ndarray = gray.astype(np.float32)
    if kind == "gray":
        return g
    b = cv2.GaussianBlur(g, (3, 3), 0)
    gx = np.asarray(cv2.Sobel(b, cv2.CV_32F, 1, 0), np.float32)
    gy = np.asarray(cv2.Sobel(b, cv2.CV_32F, 0, 1), np.float32)
    # numpy, not cv2.magnitude: OpenCV's result depends on where its output buffer starts (its
    # vector and scalar paths round differently, and numpy places the buffer anew each run), so
    # the same frames gave other ranks from run to run; IEEE products, sum and square root give
    # the same bits on every run and every CPU
    gx *= gx
    gy *= gy
    gx += gy
    return np.sqrt(gx, out=gx)

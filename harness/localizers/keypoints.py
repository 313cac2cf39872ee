"""Keypoint localization: which parts of the new view find a consistent match in the map frame.

One level further down the paper's idea (docs/decisions.md, *Keypoint localization*): a keypoint of
the query frame *localizes* when it has a ratio-test match in its paired map frame that agrees
with the pair's epipolar geometry (a fundamental matrix by ``cv2.findFundamentalMat`` with
``USAC_MAGSAC``, which parallax does not break; a homography where the config declares the scene
planar). A box's ``r`` is the share of its keypoints that do not localize, read from a smoothed
map of that share: Gaussian densities (sigma a share of the frame's diagonal) of the keypoints
that do not localize over those of all keypoints plus a prior of ``prior`` keypoints, so that a
box with no texture is no change. The same from map to query: a map keypoint that does not
localize in the query frame is carried into the query frame by the displacement of its nearest
inlier match, so that a removed object counts. Every size is a share of the frame.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from harness import features
from harness.features import extractor, norm_of
from harness.localizers.config import KeypointConfig
from harness.localizers.local import pair_images, unit_ranks, work_image


@dataclass(frozen=True)
class PairGeometry:
    """What the pair's geometry was: the model fitted, its inliers and the matches tried."""

    model: str  # "fundamental", "homography" or "none" (too few matches: every match localizes)
    inliers: int
    matches: int
    query_keypoints: int
    map_keypoints: int


def detect(gray: np.ndarray, kc: KeypointConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """(n, 2) keypoint positions and their descriptors (None where there are none)."""
    kps, desc = extractor(kc.features, kc.max_keypoints).detectAndCompute(gray, None)
    if kc.features == "akaze" and len(kps) > kc.max_keypoints:  # strongest first, as the others
        order = np.argsort([-k.response for k in kps], kind="stable")[: kc.max_keypoints]
        kps, desc = [kps[i] for i in order], desc[order]
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    return xy, desc


def ratio_matches(a: np.ndarray | None, b: np.ndarray | None, kc: KeypointConfig) -> np.ndarray:
    """(m, 2) index pairs (i in a, j in b) passing ``kc``'s ratio test (:mod:`harness.features`)."""
    return features.ratio_matches(a, b, kc.ratio, norm_of(kc.features))


def union_matches(a: np.ndarray | None, b: np.ndarray | None, kc: KeypointConfig) -> np.ndarray:
    """The matches of both directions together (``union``, :mod:`harness.features`)."""
    return features.match(a, b, kc.ratio, norm_of(kc.features), "union")


#: The keypoints this process detected, by the work image's bytes and the detector's settings,
#: newest last: a frame's keypoints serve every stage that works on the same pixels (the ranks,
#: the registration, the no-change null's pairs). At most :data:`STORE_BYTES` of them are kept.
_STORE: OrderedDict[tuple[Any, ...], tuple[tuple[np.ndarray, np.ndarray | None], Any]] = (
    OrderedDict()
)
_STORE_LOCK = threading.Lock()
STORE_BYTES = 256 * 2**20
_stored = [0]


def _size(found: tuple[np.ndarray, np.ndarray | None]) -> int:
    return int(found[0].nbytes + (found[1].nbytes if found[1] is not None else 0))


def _packed(found: tuple[np.ndarray, np.ndarray | None]) -> tuple[np.ndarray, np.ndarray | None]:
    """``found`` as the store keeps it, its descriptors as bytes where that loses nothing.

    SIFT's float descriptors hold whole numbers 0-255: as bytes they take a quarter of the memory,
    so the 1,200 frames of two folders of 600 stay in the store from the ranks to the registration
    (:func:`_unpacked` gives the same floats back).
    """
    xy, d = found
    if d is not None and d.dtype == np.float32 and len(d):
        small = d.astype(np.uint8)
        if np.array_equal(small, d):
            return xy, small
    return found


def _unpacked(
    kept: tuple[np.ndarray, np.ndarray | None], dtype: Any
) -> tuple[np.ndarray, np.ndarray | None]:
    xy, d = kept
    return (xy, d.astype(dtype)) if d is not None and d.dtype != dtype else kept


def stored_keypoints(gray: np.ndarray, kc: KeypointConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`detect` on ``gray``, or the keypoints this process found on the same pixels before.

    Keyed by a digest of the image's bytes and shape and the detector's settings, so nothing but
    the same pixels under the same settings can hit (the same keypoints: detection is a function
    of them).
    """
    g = np.ascontiguousarray(gray)
    digest = hashlib.blake2b(g.data, digest_size=16).digest()
    key = (digest, g.shape, str(g.dtype), kc.features, kc.max_keypoints)
    with _STORE_LOCK:
        if key in _STORE:
            _STORE.move_to_end(key)
            kept, dtype = _STORE[key]
            return _unpacked(kept, dtype)
    got = detect(g, kc)
    with _STORE_LOCK:
        if key not in _STORE:
            kept = _packed(got)
            _STORE[key] = (kept, got[1].dtype if got[1] is not None else None)
            _stored[0] += _size(kept)
            while _stored[0] > STORE_BYTES and len(_STORE) > 1:
                _stored[0] -= _size(_STORE.popitem(last=False)[1][0])
    return got


class MapFeatures:
    """A unit's frames' keypoints, detected once however many pairs hold one.

    Map frames shared by several query frames, and the no-change null's query frames (a map frame
    against several perturbed copies of itself) are detected once: the same keypoints, once; and
    across units and stages of one process, once a work image (:func:`stored_keypoints`).

    Keyed by the map image and the work size; two threads asking for one frame at once may both
    detect it (the same keypoints), never a wrong one. ``detected`` counts the frames asked for.
    """

    def __init__(self, kc: KeypointConfig) -> None:
        self.kc = kc
        self.found: dict[tuple[str, tuple[int, ...]], tuple[np.ndarray, np.ndarray | None]] = {}
        self.detected = 0
        self._lock = threading.Lock()

    def of(self, uri: str, m: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The keypoints of map image ``uri`` worked on as ``m``."""
        key = (uri, m.shape)
        with self._lock:
            if key in self.found:
                return self.found[key]
        got = stored_keypoints(m, self.kc)
        with self._lock:
            self.detected += 1
            return self.found.setdefault(key, got)


def localized(
    q: np.ndarray,
    m: np.ndarray,
    kc: KeypointConfig,
    map_features: tuple[np.ndarray, np.ndarray | None] | None = None,
    query_features: tuple[np.ndarray, np.ndarray | None] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, PairGeometry]:
    """Keypoints of two gray frames of one size and which of them localize in the other.

    Returns the query's (n, 2) positions and flags, the map's (k, 2) positions carried into the
    query frame (by their nearest inlier match's displacement) and flags, and the geometry.
    ``map_features``, ``query_features``: ``m``'s and ``q``'s keypoints and descriptors where they
    were detected before.
    """
    xq, dq = query_features if query_features is not None else detect(q, kc)
    xm, dm = map_features if map_features is not None else detect(m, kc)
    both = union_matches(dq, dm, kc)  # (query index, map index)
    ok_q, ok_m = np.zeros(len(xq), bool), np.zeros(len(xm), bool)
    geo = PairGeometry("none", 0, len(both), len(xq), len(xm))
    inl = np.zeros(len(both), bool)
    diag = float(np.hypot(*q.shape[:2]))
    if len(both) >= kc.min_matches:
        p1, p2 = xq[both[:, 0]].astype(np.float32), xm[both[:, 1]].astype(np.float32)
        thr = max(0.5, kc.ransac_threshold * diag)
        try:
            if kc.geometry == "homography":
                model, mask = cv2.findHomography(p2, p1, cv2.USAC_MAGSAC, thr, maxIters=2000,
                                                 confidence=0.999)  # fmt: skip
            else:
                model, mask = cv2.findFundamentalMat(p1, p2, cv2.USAC_MAGSAC, thr, 0.999, 2000)
        except cv2.error:  # USAC asserts on some degenerate sets (all matches on one plane
            model, mask = None, None  # under a pure shift): no geometry, as when none is found
        if model is not None and mask is not None and model.shape[:2] == (3, 3):
            inl = mask.ravel().astype(bool)
            geo = PairGeometry(kc.geometry, int(inl.sum()), len(both), len(xq), len(xm))
    if geo.model == "none":
        inl[:] = True  # no geometry to check: a ratio-test match is all the evidence there is
    ok_q[both[inl, 0]] = True
    ok_m[both[inl, 1]] = True
    carried = xm.copy()
    if inl.any():  # each map keypoint moved by the displacement of its nearest inlier match
        src = xm[both[inl, 1]]
        shift = xq[both[inl, 0]] - src
        d2 = ((xm[:, None, :] - src[None, :, :]) ** 2).sum(-1)
        carried = xm + shift[np.argmin(d2, axis=1)]
    return xq, ok_q, carried, ok_m, geo


def share_map(
    shape: tuple[int, int],
    points: np.ndarray,
    lost: np.ndarray,
    kc: KeypointConfig,
) -> np.ndarray:
    """The smoothed share of keypoints that do not localize, per pixel of a frame of ``shape``.

    ``points``: (n, 2) positions (query frame); ``lost``: which do not localize. Each keypoint is
    an impulse of 1 blurred by a Gaussian of peak 1 (sigma ``kc.sigma`` of the frame's diagonal);
    the share is lost density over all density plus ``kc.prior`` keypoints' peak.
    """
    h, w = shape
    sigma = max(0.5, kc.sigma * float(np.hypot(h, w)))
    allm, lostm = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    ij = np.round(points).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    np.add.at(allm, (ij[inside, 1], ij[inside, 0]), 1.0)
    np.add.at(lostm, (ij[inside & lost, 1], ij[inside & lost, 0]), 1.0)
    k = int(2 * round(3 * sigma) + 1)
    peak = 2.0 * np.pi * sigma * sigma  # GaussianBlur sums to 1: scale so a lone point peaks at 1
    allm = cv2.GaussianBlur(allm, (k, k), sigma, borderType=cv2.BORDER_CONSTANT) * peak
    lostm = cv2.GaussianBlur(lostm, (k, k), sigma, borderType=cv2.BORDER_CONSTANT) * peak
    return lostm / (allm + kc.prior)


def box_shares(smap: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Each box's mean of the share map (boxes in ``smap``'s pixels); NaN for an empty box."""
    ii = cv2.integral(smap.astype(np.float64))
    h, w = smap.shape
    x1, y1, x2, y2 = np.asarray(boxes, np.float64).reshape(-1, 4).T
    a, b = np.clip(np.floor(x1), 0, w).astype(np.intp), np.clip(np.floor(y1), 0, h).astype(np.intp)
    c, d = np.clip(np.ceil(x2), 0, w).astype(np.intp), np.clip(np.ceil(y2), 0, h).astype(np.intp)
    out = np.full(len(x1), np.nan)
    k = (c > a) & (d > b)  # every box at once, each sum in the order one box's was taken
    a, b, c, d = a[k], b[k], c[k], d[k]
    out[k] = (ii[d, c] - ii[b, c] - ii[d, a] + ii[b, a]) / ((c - a) * (d - b)).astype(np.float64)
    return out


def pair_shares(
    q: np.ndarray,
    m: np.ndarray,
    boxes: np.ndarray,
    kc: KeypointConfig,
    map_features: tuple[np.ndarray, np.ndarray | None] | None = None,
    query_features: tuple[np.ndarray, np.ndarray | None] | None = None,
) -> tuple[np.ndarray, PairGeometry]:
    """Each box's share of keypoints that do not localize (both directions), and the geometry.

    ``q``, ``m``: the pair's gray work images of one size; ``boxes``: (n, 4) in their pixels.
    """
    xq, ok_q, xm, ok_m, geo = localized(q, m, kc, map_features, query_features)
    if kc.both_directions:
        pts, lost = np.concatenate([xq, xm]), np.concatenate([~ok_q, ~ok_m])
    else:
        pts, lost = xq, ~ok_q
    return box_shares(share_map(q.shape[:2], pts, lost, kc), boxes), geo


#: The counters of a unit of keypoint ranks.
KEYPOINT_COUNTS = (
    "query_subimages",
    "ranked",
    "no_rank_box_outside",
    "pairs_fundamental",
    "pairs_homography",
    "pairs_none",
)


def work_gray(uri: str, width: int, height: int, side: int) -> tuple[np.ndarray, float]:
    """A frame's gray work image, its longer side at most ``side``, and its scale."""
    gray, _ = work_image(uri, width, height, side)
    longer = max(gray.shape)
    if longer > side:
        f = side / float(longer)
        size = (max(1, round(gray.shape[1] * f)), max(1, round(gray.shape[0] * f)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    return gray, gray.shape[1] / float(width)


def pair_keypoint_ranks(
    q_uri: str,
    m_uri: str,
    size: tuple[int, int],
    boxes: np.ndarray,
    kc: KeypointConfig,
    maps: MapFeatures | None = None,
) -> tuple[PairGeometry, np.ndarray]:
    """One pair's geometry and each query box's (rank, L, 1 - share); NaN rows where none.

    ``size``: the frames' (width, height); ``boxes``: (n, 4) in frame pixels; ``maps``: the map
    frames' keypoints already detected (a unit's).
    """
    q, m, s = pair_images(q_uri, m_uri, size, kc.work_side, work_gray)
    feats = maps.of(m_uri, m) if maps is not None else None
    qfeats = maps.of(q_uri, q) if maps is not None else None
    share, geo = pair_shares(
        q, m, np.asarray(boxes, np.float64).reshape(-1, 4) * s, kc, feats, qfeats
    )
    out = np.full((len(share), 3), np.nan)
    ok = np.isfinite(share)
    rank = 1 + np.round(np.clip(share[ok], 0, 1) * (kc.levels - 1))
    out[ok] = np.column_stack([rank, np.full(len(rank), kc.levels), 1.0 - share[ok]])
    return geo, out


def write_keypoint_ranks(
    kc: KeypointConfig, pairs: Any, frames: Any, props: Any, tmp: Path
) -> dict[str, int]:
    """One unit's rank rows (``ranks.parquet``) and each pair's geometry (``alignment.parquet``).

    ``align`` the model, ``inliers``, ``align_score`` the inliers' share of the matches.
    """
    maps = MapFeatures(kc)  # a map frame's keypoints once, however many queries pair with it

    def one(q_img: str, m_img: str, wh: tuple[int, int], xy: np.ndarray) -> tuple[tuple, Any]:
        geo, got = pair_keypoint_ranks(q_img, m_img, wh, xy, kc, maps)
        score = geo.inliers / geo.matches if geo.matches else 0.0
        return (geo.model, geo.inliers, score), got

    return unit_ranks(one, pairs, frames, props, tmp, KEYPOINT_COUNTS, "no_rank_box_outside")

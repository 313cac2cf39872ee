"""The plain difference by the reference recipe: ``[detect.difference] recipe = "reference"``.

docs/method.md, *The plain difference*. A training-free difference with no localizer, written
from the method's words; on the 51 real revisits of ``obchange-rooms`` it agrees with a reference
run of the same words pair by pair (the same registration verdict on every pair, change maps that
correlate at least 0.9, 8 or more of each pair's top 10 boxes the same on 50 pairs:
``python -m bench.plain_agreement``). Every length is in pixels of a 640 x 480 frame (a diagonal
of 800) and scales with the frame's diagonal.

1. **Register** (:func:`register_reference`): SIFT on the grey frames (every keypoint, contrast
   threshold 0.02, three octave layers), RootSIFT, query-to-map nearest two, ratio 0.8; a
   homography from query to map pixels by MAGSAC (6 px, 5,000 iterations, confidence 0.999). The
   pair is registered with at least ``min_inliers`` inliers, 30% of the query frame inside the
   warped map frame, and the determinant of the homography's upper 2 x 2 (over its corner) within
   [0.2, 5].
2. **Change map of a registered pair** (:func:`registered_map`): the map frame warped into the
   query's; valid pixels inside it, eroded by 9 x 9; both frames in CIELAB (float); the map's L, a
   and b matched to the query's by gain and offset over the valid pixels; each pixel's smallest
   weighted distance sqrt((0.5 dL)^2 + da^2 + db^2) over shifts of the warped map by {-2, 0, +2} px
   each way, over 25, clipped to [0, 1]; 0 outside the valid pixels; a Gaussian blur (sigma 4)
   over the blurred validity, 0 outside again.
3. **Change map of a pair that is not registered** (:func:`colour_map`, ``not_comparable =
   "fallback"``): the colours' novelty, no geometry: each query pixel's log ratio of its colour's
   probability in the query frame to that in the map frame (Lab histograms of 8 x 24 x 24 bins over
   L [0, 100], a and b [-64, 64], each smoothed by a Gaussian of one bin), over 3, clipped to
   [0, 1], then the same blur.
4. **Boxes** (:func:`reference_boxes`): every box of Selective Search on the query's copy
   ``[proposals.selective] work_width`` wide; boxes under 12 px wide or high, or over 40% of the
   frame, dropped.
5. **Score** (:func:`ring_contrast`): the map's mean inside the box less its mean in the ring
   around it (the box grown by a quarter of its width and height each side, at least 4 px, clipped
   to the frame); plus :data:`REGISTERED_TIER` on a registered pair, so that every registered
   pair's boxes rank above every other pair's in the pooled ranking (a pair that cannot be
   registered is read by colour alone, a weaker cue).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import cv2
import numpy as np

from harness.detect.difference import (
    Registration,
    parallax_residual,
    scaled_copy,
    to_gray,
    warped_footprint,
)
from harness.proposals.builtin import selective_rects, working_copy

#: The frame the recipe's lengths are given for: 640 x 480, a diagonal of 800 pixels.
REFERENCE_DIAGONAL = 800.0
#: Added to every box score of a registered pair: registered pairs rank first.
REGISTERED_TIER = 2.0
#: SIFT's settings and the ratio test.
SIFT_CONTRAST, SIFT_LAYERS, RATIO = 0.02, 3, 0.8
#: MAGSAC: threshold (px at 640 x 480), iterations, confidence.
MAGSAC = (6.0, 5000, 0.999)
#: Registered: the share of the query frame inside the warped map, and the determinant's range.
MIN_INSIDE, DET_RANGE = 0.3, (0.2, 5.0)
#: The change map (px at 640 x 480): erosion, shift, distance scale, blur; L's weight: (0.5 dL)^2.
ERODE, SHIFT, DISTANCE_SCALE, BLUR, L_WEIGHT = 9, 2, 25.0, 4.0, 0.25
#: The colours' novelty: histogram bins and ranges, their smoothing (bins), the log ratio's scale.
NOVELTY_BINS = (8, 24, 24)
NOVELTY_RANGE = ((0.0, 100.0), (-64.0, 64.0), (-64.0, 64.0))
NOVELTY_SMOOTH, NOVELTY_EPS, NOVELTY_SCALE = 1.0, 1e-5, 3.0
#: Candidate boxes: the narrowest side (px at 640 x 480) and the largest share of the frame.
MIN_BOX_SIDE, MAX_BOX_SHARE = 12.0, 0.4
#: The ring: a share of the box each side, at least this many px at 640 x 480.
RING, RING_MIN = 0.25, 4.0


def _px(length: float, shape: tuple[int, ...]) -> float:
    """``length`` pixels of a 640 x 480 frame, in a frame of ``shape``."""
    return length * float(np.hypot(shape[0], shape[1])) / REFERENCE_DIAGONAL


#: Frames whose RootSIFT this process keeps (about 0.5 MB each at 640 x 480), the least recently
#: used dropped first: a frame registered in several runs of one process (a map's frames against
#: a new session and against themselves) is detected once.
STORE_FRAMES = 256
_STORE: OrderedDict[bytes, tuple[np.ndarray, np.ndarray | None]] = OrderedDict()
_STORE_LOCK = threading.Lock()


def stored_root_sift(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`root_sift` of ``gray``, or what this process found on the same pixels before.

    Keyed by a digest of the pixels and the shape, so the same frame under two names (or read
    twice) is detected once; the values are :func:`root_sift`'s own, so the store changes no
    output.
    """
    g = np.ascontiguousarray(gray)
    key = hashlib.blake2b(g.data, digest_size=20, salt=str(g.shape).encode()[:16]).digest()
    with _STORE_LOCK:
        if key in _STORE:
            _STORE.move_to_end(key)
            return _STORE[key]
    got = root_sift(g)
    with _STORE_LOCK:
        _STORE[key] = got
        while len(_STORE) > STORE_FRAMES:
            _STORE.popitem(last=False)
    return got


def forget_root_sift() -> None:
    """Empty this process's store (:func:`stored_root_sift`): the next frames are detected anew."""
    with _STORE_LOCK:
        _STORE.clear()


class RootSift:
    """RootSIFT keypoints of a run's grey frames by their URIs (:func:`stored_root_sift` below).

    One instance serves a run's pairs side by side (a map frame shared by several pairs, the
    null's frames): the lock guards the dictionary, never the detection.
    """

    def __init__(self) -> None:
        self._got: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        self._lock = threading.Lock()

    def of(self, uri: str, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The keypoints' (n, 2) positions and (n, 128) RootSIFT descriptors of ``gray``."""
        with self._lock:
            if uri in self._got:
                return self._got[uri]
        got = stored_root_sift(gray)
        with self._lock:
            return self._got.setdefault(uri, got)


def root_sift(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT (every keypoint) with RootSIFT descriptors: L1-normalised, square-rooted."""
    make = cv2.SIFT_create  # type: ignore[attr-defined]
    sift = make(nfeatures=0, nOctaveLayers=SIFT_LAYERS, contrastThreshold=SIFT_CONTRAST)
    kp, d = sift.detectAndCompute(gray, None)
    if d is None or not len(kp):
        return np.zeros((0, 2), np.float32), None
    d = d / (np.abs(d).sum(1, keepdims=True) + 1e-7)
    return np.array([k.pt for k in kp], np.float32), np.sqrt(d).astype(np.float32)


def register_reference(
    q_rgb: np.ndarray,
    m_rgb: np.ndarray,
    min_inliers: int,
    side: int = 640,
    features: tuple[RootSift, str, str] | None = None,
) -> Registration:
    """The recipe's registration (step 1): ``H`` maps map pixels to query pixels (full size).

    Both frames are registered on copies whose longer side is at most ``side`` pixels
    (``[detect.difference] register_side``: 640, the recipe's own 640 x 480 frames as they are).
    """
    (q, fq), (m, fm) = scaled_copy(to_gray(q_rgb), side), scaled_copy(to_gray(m_rgb), side)
    if features is not None:
        cache, q_uri, m_uri = features
        (xq, dq), (xm, dm) = cache.of(f"{q_uri}@{side}", q), cache.of(f"{m_uri}@{side}", m)
    else:
        (xq, dq), (xm, dm) = stored_root_sift(q), stored_root_sift(m)
    if dq is None or dm is None or len(dm) < 2:
        return Registration(None, 0, 0, 0.0, "too few matches (0)", "none")
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dq, dm, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    n = len(good)
    if n < max(4, min_inliers):
        return Registration(None, 0, n, 0.0, f"too few matches ({n})", "none")
    src = np.array([xq[g.queryIdx] for g in good], np.float32)
    dst = np.array([xm[g.trainIdx] for g in good], np.float32)
    thr, iters, conf = MAGSAC
    try:
        H_qm, mask = cv2.findHomography(
            src, dst, cv2.USAC_MAGSAC, _px(thr, q.shape), maxIters=iters, confidence=conf
        )
    except cv2.error:
        H_qm, mask = None, None
    if H_qm is None or mask is None or abs(H_qm[2, 2]) < 1e-12:
        return Registration(None, 0, n, 0.0, "no homography found", "none")
    if not np.isfinite(H_qm).all() or abs(np.linalg.det(H_qm)) < 1e-12:
        return Registration(None, int(mask.sum()), n, 0.0, "a degenerate warp (singular)", "none")
    inliers = int(mask.sum())
    # what the homography leaves (parallax), a share of the diagonal, as the null draws it
    residual = parallax_residual(src, dst, H_qm, mask, _px(thr, q.shape))
    residual /= float(np.hypot(*q.shape[:2]))
    foot = float(warped_footprint(np.linalg.inv(H_qm), m.shape[:2], q.shape[:2]).mean())
    # back to full-size pixels: query pixels -> work query -> work map -> map pixels
    H_qm = np.diag([1 / fm, 1 / fm, 1.0]) @ H_qm @ np.diag([fq, fq, 1.0])
    H = np.linalg.inv(H_qm)
    det = float(np.linalg.det(H_qm[:2, :2] / H_qm[2, 2]))
    if inliers < min_inliers:
        why = f"too few inliers ({inliers} < {min_inliers})"
    elif not DET_RANGE[0] <= det <= DET_RANGE[1]:
        why = f"a degenerate warp (determinant {det:.2f} outside [{DET_RANGE[0]}, {DET_RANGE[1]}])"
    elif foot < MIN_INSIDE:
        why = f"the warped map covers {foot:.0%} of the frame (< {MIN_INSIDE:.0%})"
    else:
        why = ""
    return Registration(H, inliers, n, foot, why, residual=round(residual, 6))


def _lab(rgb: np.ndarray) -> np.ndarray:
    """CIELAB in floats (L in [0, 100]) of an RGB frame."""
    return cv2.cvtColor(np.ascontiguousarray(rgb, np.float32) / 255.0, cv2.COLOR_RGB2Lab)


def _blur(x: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """``x`` blurred over the blurred ``valid`` (so pixels outside it take part in nothing)."""
    v = valid.astype(np.float32)
    num = cv2.GaussianBlur(x * v, (0, 0), sigma)
    return num / np.maximum(cv2.GaussianBlur(v, (0, 0), sigma), 1e-6)


def registered_map(q_rgb: np.ndarray, m_rgb: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Step 2: the change map of a registered pair, in [0, 1], the query frame's size."""
    h, w = q_rgb.shape[:2]
    m8 = np.ascontiguousarray(m_rgb, np.uint8)
    H_qm = np.linalg.inv(H)
    warped = cv2.warpPerspective(m8, H_qm, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    ones = np.full(m8.shape[:2], 255, np.uint8)
    inside = cv2.warpPerspective(ones, H_qm, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
    k = max(1, round(_px(ERODE, (h, w)))) | 1  # odd: 9 at 640 x 480
    valid = cv2.erode((inside > 0).astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    ql, ml = _lab(q_rgb), _lab(warped)
    q = [np.ascontiguousarray(ql[..., c]) for c in range(3)]
    mp = [np.ascontiguousarray(ml[..., c]) for c in range(3)]
    if valid.sum() > 1:  # the map's gain and offset onto the query's, channel by channel
        mask = valid.astype(np.uint8)
        for c in range(3):
            qm, qs = (float(x[0, 0]) for x in cv2.meanStdDev(q[c], mask=mask))
            mm, ms = (float(x[0, 0]) for x in cv2.meanStdDev(mp[c], mask=mask))
            gain = qs / (ms + 1e-6)
            mp[c] = ((mp[c] - np.float32(mm)) * np.float32(gain) + np.float32(qm)).astype(
                np.float32
            )
    best = _least_distance(q, mp, max(1, round(_px(SHIFT, (h, w)))))
    dmap = np.clip(np.sqrt(best) / DISTANCE_SCALE, 0.0, 1.0).astype(np.float32)
    dmap[~valid] = 0.0
    out = _blur(dmap, valid, max(0.5, _px(BLUR, (h, w))))
    out[~valid] = 0.0
    return out.astype(np.float32)


def _least_distance(q: list[np.ndarray], m: list[np.ndarray], s: int) -> np.ndarray:
    """Each pixel's least weighted squared Lab distance to ``m`` moved by -s, 0 or s each way.

    Channel planes; the map's edges repeated as it moves; (0.5 dL)^2 + da^2 + db^2, by OpenCV's
    elementwise calls on reused buffers.
    """
    h, w = q[0].shape
    pad = [cv2.copyMakeBorder(x, s, s, s, s, cv2.BORDER_REPLICATE) for x in m]
    best = np.full((h, w), np.inf, np.float32)
    acc, d = np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    for dy in (-s, 0, s):
        for dx in (-s, 0, s):
            for c in range(3):
                cv2.subtract(q[c], pad[c][s + dy : s + dy + h, s + dx : s + dx + w], dst=d)
                if c == 0:
                    cv2.multiply(d, d, dst=acc, scale=L_WEIGHT)
                else:
                    cv2.multiply(d, d, dst=d)
                    cv2.add(acc, d, dst=acc)
            cv2.min(best, acc, dst=best)
    return best


def colour_map(q_rgb: np.ndarray, m_rgb: np.ndarray) -> np.ndarray:
    """Step 3: the colours' novelty of a pair that is not registered, in [0, 1]."""
    from scipy.ndimage import gaussian_filter

    def bins(lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each pixel's flat bin, and whether it lies in the histogram's range."""
        flat, inside = np.zeros(lab.shape[:2], np.int64), np.ones(lab.shape[:2], bool)
        for c, ((lo, hi), n) in enumerate(zip(NOVELTY_RANGE, NOVELTY_BINS, strict=True)):
            x = lab[..., c]
            inside &= (x >= lo) & (x <= hi)  # the last bin holds its upper edge, as numpy's
            flat = flat * n + np.clip(((x - lo) * (n / (hi - lo))).astype(np.int64), 0, n - 1)
        return flat, inside

    def probability(flat: np.ndarray, inside: np.ndarray) -> np.ndarray:
        count = np.bincount(flat[inside], minlength=int(np.prod(NOVELTY_BINS)))
        hist = gaussian_filter(count.reshape(NOVELTY_BINS).astype(np.float64), NOVELTY_SMOOTH)
        return (hist / max(hist.sum(), 1e-12)).reshape(-1)

    fq, iq = bins(_lab(q_rgb))
    pq, pm = probability(fq, iq), probability(*bins(_lab(m_rgb)))
    ratio = np.log((pq[fq] + NOVELTY_EPS) / (pm[fq] + NOVELTY_EPS)) / NOVELTY_SCALE
    out = np.clip(ratio, 0.0, 1.0).astype(np.float32)
    return cv2.GaussianBlur(out, (0, 0), max(0.5, _px(BLUR, out.shape)))


def reference_boxes(rgb: np.ndarray, work_width: int, mode: str, seed: int) -> np.ndarray:
    """Step 4: every Selective Search box of the frame, less the thin and the huge; (k, 4)."""
    h, w = rgb.shape[:2]
    small, scale = working_copy(rgb, work_width)
    rects = selective_rects(cv2.cvtColor(small, cv2.COLOR_RGB2BGR), mode, seed)
    if not len(rects):
        return np.zeros((0, 4))
    boxes = np.column_stack([rects[:, :2], rects[:, :2] + rects[:, 2:]]) / scale
    bw, bh = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    side = _px(MIN_BOX_SIDE, (h, w))
    keep = (bw >= side) & (bh >= side) & (bw * bh <= MAX_BOX_SHARE * w * h)
    return np.unique(boxes[keep], axis=0)


def ring_contrast(dmap: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Step 5 without the tier: each box's mean less its ring's (pixels of the rounded box)."""
    h, w = dmap.shape
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    total = cv2.integral(dmap.astype(np.float64))

    def sums(x1: np.ndarray, y1: np.ndarray, x2: np.ndarray, y2: np.ndarray) -> tuple:
        a = np.clip(np.round(x1), 0, w).astype(np.intp)
        c = np.clip(np.round(x2), 0, w).astype(np.intp)
        t = np.clip(np.round(y1), 0, h).astype(np.intp)
        d = np.clip(np.round(y2), 0, h).astype(np.intp)
        s = total[d, c] - total[t, c] - total[d, a] + total[t, a]
        return s, np.maximum((c - a) * (d - t), 0).astype(np.float64)

    x1, y1, x2, y2 = b.T
    si, ni = sums(x1, y1, x2, y2)
    least = _px(RING_MIN, (h, w))
    gw = np.maximum(RING * (x2 - x1), least)
    gh = np.maximum(RING * (y2 - y1), least)
    so, no = sums(x1 - gw, y1 - gh, x2 + gw, y2 + gh)
    inner = si / np.maximum(ni, 1.0)
    ring = (so - si) / np.maximum(no - ni, 1.0)
    return inner - ring

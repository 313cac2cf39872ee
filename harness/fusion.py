"""Fusion of subimage ranks into sample LoC values (SPEC section 7) and pixel-wise LoC maps."""

from __future__ import annotations

import numpy as np

from .config import FUSION_METHODS

FUSED_METHODS = tuple(m for m in FUSION_METHODS if m != "rank_no_fusion")


def intersection_closure(boxes: np.ndarray, max_boxes: int | None = None) -> tuple[np.ndarray, bool]:
    """The closure of ``boxes`` under pairwise intersection (positive area, duplicates merged).

    Semi-naive fixed point: each round intersects only the boxes found in the previous round
    with the originals, since every intersection of a subset is reachable one original at a
    time. Cost is O(|closure| x n) instead of re-scanning all pairs every round.

    Returns:
        (unique boxes sorted lexicographically (m, 4), capped) where ``capped`` says the closure
        was cut at ``max_boxes``.
    """
    orig = np.unique(np.asarray(boxes, np.float64).reshape(-1, 4), axis=0)
    orig = orig[(orig[:, 2] > orig[:, 0]) & (orig[:, 3] > orig[:, 1])]
    seen = {tuple(b) for b in orig}
    frontier = orig
    capped = False
    while len(frontier):
        x1 = np.maximum(frontier[:, None, 0], orig[None, :, 0])
        y1 = np.maximum(frontier[:, None, 1], orig[None, :, 1])
        x2 = np.minimum(frontier[:, None, 2], orig[None, :, 2])
        y2 = np.minimum(frontier[:, None, 3], orig[None, :, 3])
        cand = np.stack([x1, y1, x2, y2], -1).reshape(-1, 4)
        cand = cand[(cand[:, 2] > cand[:, 0]) & (cand[:, 3] > cand[:, 1])]
        cand = np.unique(cand, axis=0)
        new = [b for b in map(tuple, cand) if b not in seen]
        if max_boxes is not None and len(seen) + len(new) > max_boxes:
            new = new[: max(0, max_boxes - len(seen))]
            capped = True
        seen.update(new)
        frontier = np.array(new, np.float64).reshape(-1, 4)
        if capped:
            break
    out = np.array(sorted(seen), np.float64).reshape(-1, 4)
    return out, capped


def cover_matrix(fused: np.ndarray, originals: np.ndarray) -> np.ndarray:
    """(m, n) bool: original k contains fused box i."""
    f, o = fused[:, None, :], originals[None, :, :]
    return (o[..., 0] <= f[..., 0]) & (o[..., 1] <= f[..., 1]) & (o[..., 2] >= f[..., 2]) & (o[..., 3] >= f[..., 3])


def _subset_cover(cover: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Where a row covers more than k originals, keep a random k of them (in row order)."""
    out = cover.copy()
    for i in np.nonzero(cover.sum(1) > k)[0]:
        idx = np.nonzero(cover[i])[0]
        keep = rng.choice(idx, size=k, replace=False)
        out[i] = False
        out[i, keep] = True
    return out


def fuse(
    boxes: np.ndarray, r: np.ndarray, d: np.ndarray, method: str, seed: int = 0, max_boxes: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Samples and their LoC for one query image.

    Args:
        boxes: (n, 4) original boxes of all proposal methods.
        r: (n,) normalised ranks in (0, 1].
        d: (n,) L2 distances to the ground-truth frame.
        method: one of ``rank_fusion``, ``rank_fusion_le2``, ``rank_fusion_le3``,
            ``rank_no_fusion``, ``score_max``, ``score_sum``.
        seed: seeds the random cover subsets of the ``le`` methods.

    Returns:
        (sample_boxes (m, 4), loc (m,)).
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    r = np.asarray(r, np.float64)
    d = np.asarray(d, np.float64)
    if method == "rank_no_fusion":
        return boxes.copy(), r.copy()
    if method not in FUSED_METHODS:
        raise ValueError(f"unknown fusion method {method!r}; known: {FUSION_METHODS}")
    fused, _ = intersection_closure(boxes, max_boxes)
    cover = cover_matrix(fused, boxes)
    return fused, loc_from_cover(cover, r, d, method, seed)


def loc_from_cover(cover: np.ndarray, r: np.ndarray, d: np.ndarray, method: str, seed: int = 0) -> np.ndarray:
    """LoC of fused boxes from their cover matrix (shared by :func:`fuse` and the runner)."""
    if method == "score_max":
        return np.where(cover, d[None, :], -np.inf).max(1)
    if method == "score_sum":
        return (cover * d[None, :]).sum(1)
    if method in ("rank_fusion_le2", "rank_fusion_le3"):
        cover = _subset_cover(cover, 2 if method.endswith("2") else 3, np.random.default_rng(seed))
    n = cover.sum(1)
    inv = (cover * (1.0 / r)[None, :]).sum(1)
    return 1.0 / (n * inv)


def loc_map(sample_boxes: np.ndarray, loc: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel-wise LoC: each pixel (by its centre) takes the LoC of the smallest sample box holding it.

    For a fused set, the smallest box holding a pixel is the intersection of all boxes covering
    it. Pixels that no box covers are NaN.
    """
    out = np.full((height, width), np.nan, np.float32)
    area = (sample_boxes[:, 2] - sample_boxes[:, 0]) * (sample_boxes[:, 3] - sample_boxes[:, 1])
    for i in np.argsort(-area, kind="stable"):
        x1, y1, x2, y2 = sample_boxes[i]
        # pixel u is inside when x1 <= u + 0.5 < x2
        u0, u1 = int(np.ceil(x1 - 0.5)), int(np.ceil(x2 - 0.5))
        v0, v1 = int(np.ceil(y1 - 0.5)), int(np.ceil(y2 - 0.5))
        out[max(v0, 0) : max(min(v1, height), 0), max(u0, 0) : max(min(u1, width), 0)] = loc[i]
    return out

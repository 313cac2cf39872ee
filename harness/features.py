"""Local features in one place: detectors and descriptors by name, their norm, the matching modes.

Alignment (``harness.localizers.align``), keypoint localization (``harness.localizers.keypoints``),
the pair's registration (``harness.detect.difference``) and bag of visual words
(``harness.retrieval.bovw``) all make their features and matches here, so a detector, a norm or
a matching mode means the same thing everywhere.

Matching modes, named as feature-matching libraries name them: ``one-way`` (each feature of the
first set to its nearest in the second, kept where it passes Lowe's ratio test), ``union`` (the
one-way matches of both directions together, each pair once: more matches on a textured scene,
which the geometry then sorts) and ``mutual`` (those that pass both ways).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

#: The detectors and descriptors by name: SIFT (float descriptors), ORB and AKAZE (binary).
FEATURES = ("sift", "orb", "akaze")
#: The matching modes (module docstring).
MATCHING = ("one-way", "union", "mutual")


def extractor(name: str, max_keypoints: int | None = None, **orb: Any) -> cv2.Feature2D:
    """OpenCV's detector and descriptor ``name``.

    It keeps at most ``max_keypoints`` (SIFT, ORB; AKAZE keeps all: cut its strongest
    afterwards); ``orb``: ORB's own parameters.
    """
    if name == "orb":
        n = max_keypoints if max_keypoints is not None else 500
        return cv2.ORB_create(nfeatures=n, **orb)  # type: ignore[attr-defined]
    if name == "akaze":
        return cv2.AKAZE_create()  # type: ignore[attr-defined]
    if name != "sift":
        raise ValueError(f"local features {name!r}: one of {', '.join(FEATURES)}")
    if max_keypoints is None:
        return cv2.SIFT_create()  # type: ignore[attr-defined]
    return cv2.SIFT_create(nfeatures=max_keypoints)  # type: ignore[attr-defined]


def norm_of(name: str) -> int:
    """The descriptors' distance: L2 for SIFT's floats, Hamming for ORB's and AKAZE's bits."""
    return cv2.NORM_L2 if name == "sift" else cv2.NORM_HAMMING


def ratio_matches(
    a: np.ndarray | None, b: np.ndarray | None, ratio: float, norm: int
) -> np.ndarray:
    """(m, 2) index pairs (i in ``a``, j in ``b``) whose nearest neighbour passes the ratio test.

    Closer than ``ratio`` times the second nearest (brute force, k = 2), in ``a``'s order.
    """
    if a is None or b is None or len(a) < 1 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    knn = cv2.BFMatcher(norm).knnMatch(a, b, k=2)
    out = [(m.queryIdx, m.trainIdx) for m, n in (p for p in knn if len(p) == 2)
           if m.distance < ratio * n.distance]  # fmt: skip
    return np.array(out, np.int64).reshape(-1, 2)


def match(
    a: np.ndarray | None, b: np.ndarray | None, ratio: float, norm: int, mode: str = "union"
) -> np.ndarray:
    """(m, 2) index pairs (i in ``a``, j in ``b``) by the matching ``mode`` (:data:`MATCHING`).

    ``union`` and ``mutual`` are sorted by (i, j) and hold each pair once; ``union`` with no
    match from ``b`` to ``a`` is the one-way matches as they come.
    """
    fwd = ratio_matches(a, b, ratio, norm)
    if mode == "one-way":
        return fwd
    back = ratio_matches(b, a, ratio, norm)[:, ::-1]
    if mode == "mutual":
        both = {tuple(x) for x in back.tolist()}
        keep = np.array([tuple(x) in both for x in fwd.tolist()], bool)
        return np.unique(fwd[keep], axis=0) if keep.any() else np.zeros((0, 2), np.int64)
    if mode != "union":
        raise ValueError(f"matching mode {mode!r}: one of {', '.join(MATCHING)}")
    united = np.concatenate([fwd, back]) if len(back) else fwd
    return np.unique(united, axis=0) if len(united) else united

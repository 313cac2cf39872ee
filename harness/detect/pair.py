"""A query frame and its map frame compared once, by ``[detect.difference] recipe``.

The one place a pair is registered and differenced: the detector's boxes, Table D's plain
difference and pixel rows, the no-change null and the page's counts all read this comparison, so
one registration verdict serves them all (docs/method.md, §13.5). The reference recipe's steps
are :mod:`harness.detect.plain`; the novelty-product recipe's, :mod:`harness.detect.difference`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from harness.detect.difference import (
    box_differences,
    difference_map,
    novelty_of,
    register,
    scaled_copy,
)
from harness.detect.plain import (
    REGISTERED_TIER,
    RootSift,
    colour_map,
    register_reference,
    registered_map,
    ring_contrast,
)
from harness.localizers.keypoints import MapFeatures


class PairDifference:
    """A query frame and its map frame compared once, by ``[detect.difference] recipe``.

    ``reg``: the registration (the one verdict every part of a run reads: the detector, Table D,
    the null and the page's counts); ``made``: the change map and the query's scale on it (None
    where nothing compares the pair); ``tier``: what a registered pair's scores are lifted by
    (the reference recipe's :data:`REGISTERED_TIER`, else 0). :meth:`contrast` scores boxes of
    the query frame (NaN where nothing compares the pair); :meth:`score` adds the tier.
    """

    def __init__(
        self,
        q: np.ndarray,
        m: np.ndarray,
        opt: Any,
        feats: Any = None,
        uris: tuple[str, str] | None = None,
    ) -> None:
        self.q = q
        dc = self.dc = opt.difference
        self.novelty: Any = None
        self.tier = 0.0
        if dc.recipe == "reference":
            rs = None if feats is None or uris is None else (feats.root_sift, *uris)
            self.reg = register_reference(q, m, dc.min_inliers, dc.register_side, rs)
            self.used = self.reg
            self.made: tuple[np.ndarray, float] | None = None
            work, f = scaled_copy(q, dc.side)  # the change map's frame, and its scale
            if self.reg.comparable and self.reg.H is not None:
                to_work = np.diag([f, f, 1.0]) @ self.reg.H
                self.made, self.tier = (registered_map(work, m, to_work), f), REGISTERED_TIER
            elif opt.not_comparable == "fallback":
                self.used = dataclasses.replace(self.reg, method="colour")
                self.made = (colour_map(work, scaled_copy(m, dc.side)[0]), f)
            return
        kp = None if feats is None or uris is None else (feats.keypoints, *uris)
        self.reg = register(q, m, opt.keypoints, dc, kp)
        # compared by: the registration, or the pair as it stands (not_comparable = "fallback")
        self.used = self.reg
        if not self.reg.comparable and opt.not_comparable == "fallback":
            self.used = self.reg.fallback(q, m, dc, opt.local)
        self.made = difference_map(q, m, self.used, dc)
        self.novelty = novelty_of(q, m, dc) if self.made is not None else None

    def contrast(self, boxes: np.ndarray) -> np.ndarray:
        """Each box's plain difference, without the tier (NaN where nothing compares the pair)."""
        if self.dc.recipe != "reference":
            return box_differences(self.made, self.novelty, boxes, self.dc)
        if self.made is None:
            return np.full(len(boxes), np.nan)
        dmap, f = self.made
        return ring_contrast(dmap, np.asarray(boxes, np.float64).reshape(-1, 4) * f)

    def score(self, boxes: np.ndarray) -> np.ndarray:
        """Each box's score in the pooled ranking: its contrast plus the pair's tier."""
        return self.contrast(boxes) + self.tier


class PairFeatures:
    """The keypoints a run's pairs share, each frame's found once.

    The earlier recipe's (``[detect.keypoints]``) and the reference recipe's RootSIFT.
    """

    def __init__(self, kc: Any) -> None:
        self.keypoints = MapFeatures(kc)
        self.root_sift = RootSift()

"""A paired-frame localizer kind: each box compared with the same box of its paired map frame.

A plugin: then ``harness --plugin patch_ncc.py detect ... --localizer patch-ncc`` ranks every
box by how unlike its place in the map frame it looks (1 - the normalised cross-correlation of
the two grey crops), and the no-change null is scored the same way. The harness does the units,
the cache, the rank rows, the fusion and the boxes.
"""

from dataclasses import dataclass
from functools import partial

import cv2
import numpy as np

from harness.imagestore import read_image
from harness.localizers.kinds import paired_frame_kind, register_localizer_kind

L = 1000  # the rank's scale: a box's rank is 1 + (L - 1) * its dissimilarity


@dataclass(frozen=True)
class PatchNcc:
    """A ``patch-ncc`` localizer's options."""

    frames_per_unit: int = 64  # the pairs one cached unit holds
    min_side: int = 4  # a box narrower or shorter than this gets no rank


def pair_ranks(opts, q_uri, m_uri, size, boxes):
    """((method, inliers, score), each box's (rank, L, NCC) or NaN) for one pair."""
    q = cv2.cvtColor(read_image(q_uri), cv2.COLOR_RGB2GRAY).astype(np.float32)
    m = cv2.cvtColor(read_image(m_uri), cv2.COLOR_RGB2GRAY).astype(np.float32)
    if m.shape != q.shape:
        m = cv2.resize(m, (q.shape[1], q.shape[0]), interpolation=cv2.INTER_AREA)
    got = np.full((len(boxes), 3), np.nan)
    for i, (x1, y1, x2, y2) in enumerate(np.round(boxes).astype(int)):
        a, b = q[y1:y2, x1:x2], m[y1:y2, x1:x2]
        if min(a.shape) < opts.min_side:
            continue
        ncc = float(cv2.matchTemplate(a, b, cv2.TM_CCOEFF_NORMED)[0, 0])
        ncc = ncc if np.isfinite(ncc) else 0.0
        got[i] = (1 + round((L - 1) * (1.0 - ncc) / 2.0), L, ncc)
    return ("identity", 0, 1.0), got


def pair_function(opts):
    """The pair function of ``opts`` (what the harness calls for each pair of a unit)."""
    return partial(pair_ranks, opts)


register_localizer_kind(paired_frame_kind("patch-ncc", PatchNcc, pair_function))

"""A localizer of your own, end to end: HSV colour histograms ranked by Hellinger distance.

Run after ``harness task export`` (task directory, output CSV), then
``harness reproduce ... --import hsv=<output CSV>``: see docs/localizers.md, *Bring your own
localizer*.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

task, out = Path(sys.argv[1]), sys.argv[2]
queries = pd.read_csv(task / "queries.csv")  # one row per query subimage and reference session
refs = pd.read_csv(task / "references.csv")  # one row per reference subimage (the database)
hsv: dict[str, np.ndarray] = {}


def histogram(row) -> np.ndarray:
    """The square root of the subimage's normalised HSV histogram (Hellinger = L2 of these)."""
    if row.image not in hsv:  # image paths open upright; boxes are upright pixels
        hsv[row.image] = cv2.cvtColor(cv2.imread(row.image), cv2.COLOR_BGR2HSV)
    x1, y1, x2, y2 = (round(v) for v in (row.x1, row.y1, row.x2, row.y2))
    crop = hsv[row.image][y1:y2, x1:x2]
    h = cv2.calcHist([crop], [0, 1, 2], None, [8, 4, 4], [0, 180, 0, 256, 0, 256]).ravel()
    return np.sqrt(h / max(h.sum(), 1.0))


ref_h = np.stack([histogram(r) for r in refs.itertuples()])
rows = []
for q in queries.itertuples():
    same = (
        (refs.session == q.r_session)
        & (refs.camera == q.r_camera)
        & (refs.proposal_method == q.proposal_method)
    )
    db = refs[same]
    dist = np.linalg.norm(ref_h[db.index] - histogram(q), axis=1)
    # a frame's distance is its nearest subimage's; the list holds every frame, best first
    per_frame = pd.Series(dist, index=db.utime.to_numpy()).groupby(level=0).min()
    per_frame = per_frame.sort_values(kind="stable")
    rows.append(
        {
            **{
                c: getattr(q, c)
                for c in ("q_session", "q_camera", "q_utime", "proposal_method", "box_id")
            },
            **{c: getattr(q, c) for c in ("x1", "y1", "x2", "y2", "r_session")},
            "ranked": " ".join(str(u) for u in per_frame.index),
            "scores": " ".join(f"{d:.9g}" for d in per_frame),  # distances: smaller = closer
            "L": len(per_frame),
        }
    )
pd.DataFrame(rows).to_csv(out, index=False)
print(f"{len(rows)} ranked lists -> {out}")

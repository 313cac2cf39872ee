"""Bench case ``crops``."""

from __future__ import annotations

import numpy as np

from .common import DATA, emit, timed


def case_crops(quick: bool) -> None:
    """Crop + resize to 256x256 of 16 boxes from 1,232 x 1,616 JPEG frames (decode included)."""
    import cv2
    import pandas as pd

    from harness.descriptors.crops import iter_crops

    n = 8 if quick else 32
    d = DATA / "crops"
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        p = d / f"{i}.jpg"
        if not p.exists():
            img = cv2.GaussianBlur(rng.integers(0, 256, (1616, 1232, 3), dtype=np.uint8), (0, 0), 3)
            cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        paths.append(str(p))
    rows = []
    for p in paths:
        for _k in range(16):
            x1, y1 = rng.uniform(0, 800), rng.uniform(0, 1100)
            rows.append((p, x1, y1, x1 + rng.uniform(100, 430), y1 + rng.uniform(100, 510)))
    df = pd.DataFrame(rows, columns=["image", "x1", "y1", "x2", "y2"])
    for workers in (0, 2):
        runs = timed(
            lambda w=workers: [
                None for _ in iter_crops(df, df["image"], 256, frames_per_batch=4, num_workers=w)
            ],
            repeat=3,
        )
        emit(
            f"crop+resize[workers={workers}]",
            [len(df) / t for t in runs],
            "subimages/s",
            notes=f"{n} JPEG frames 1232x1616, 16 boxes each",
        )

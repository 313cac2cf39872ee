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
    _grid5_reduced(paths)


def _grid5_reduced(paths: list[str]) -> None:
    """grid5's five boxes per NCLT-sized JPEG frame at 256: the full frame against the frame
    decoded at the fraction every box allows (1/2 here), next to the limits measured in the same
    run: libjpeg-turbo's decode of the full frame and of its half."""
    import cv2
    import pandas as pd

    from harness.descriptors.crops import iter_crops
    from harness.proposals.proposers import grid5

    boxes = grid5(1232, 1616)
    df = pd.DataFrame(
        [(p, *b) for p in paths for b in boxes], columns=["image", "x1", "y1", "x2", "y2"]
    )
    n = len(paths)
    for reduced in (False, True):
        runs = timed(
            lambda r=reduced: [None for _ in iter_crops(df, df["image"], 256, reduced=r)],
            repeat=3,
        )
        emit(
            f"grid5 crops[decode={'reduced' if reduced else 'full'}]",
            [1000 * t / n for t in runs],
            "ms/frame",
            notes=f"{n} JPEG frames 1232x1616, grid5 (centre 410x538, four of 821x1077) to 256",
        )
    for flag, name in ((cv2.IMREAD_UNCHANGED, "full"), (cv2.IMREAD_REDUCED_COLOR_2, "1/2")):
        runs = timed(lambda f=flag: [cv2.imread(p, f) for p in paths], repeat=3)
        emit(
            f"jpeg decode[{name}] (limit)",
            [1000 * t / n for t in runs],
            "ms/frame",
            notes="cv2.imread alone (libjpeg-turbo): the decode floor of the row above",
        )

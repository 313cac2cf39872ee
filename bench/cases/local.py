"""Bench case ``local``: the local localizer (method §13.3) per NCLT-sized query frame, on 2 cores.

Pairs of 1,232 x 1,616 JPEG frames (a textured scene and the same scene moved a few pixels with
objects pasted in), 60 boxes per frame (the order of ``segments``' colour regions), through
:func:`harness.localizers.local.write_local_ranks` (reduced decode, alignment, matching both ways,
the rank rows written) with the default options. Next to it, in the same run, the limits of its
kernels at the sizes it works on: the reduced JPEG decode of two frames, and the
``cv2.matchTemplate`` calls on the same windows. Reported against the paper's 25.41 ms per image.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from harness.localizers.align import feature_image
from harness.localizers.config import LocalConfig
from harness.localizers.local import write_local_ranks

from .common import emit, pair_tables

PAPER_MS = 25.41
W, H = 1232, 1616
BOXES = 60


def _frames(root: Path, n: int) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(0)
    rows, pairs, props = [], [], []
    for i in range(n):
        small = rng.integers(0, 256, (H // 16, W // 16, 3)).astype(np.uint8)
        m = cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)
        q = np.roll(m, (8, 12), axis=(0, 1)).copy()
        for _ in range(3):
            x, y = int(rng.integers(0, W - 200)), int(rng.integers(0, H - 200))
            q[y : y + 160, x : x + 120] = rng.integers(0, 256, 3)
        for s, img in (("map", m), ("query", q)):
            path = root / f"{s}{i}.jpg"
            cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
            rows.append((s, "Cam5", i, str(path), W, H))
        pairs.append(("query", "Cam5", i, "map", "Cam5", i, "SP-WI"))
        for b in range(BOXES):
            x, y = int(rng.integers(0, W - 400)), int(rng.integers(0, H - 400))
            bw, bh = int(rng.integers(40, 400)), int(rng.integers(40, 400))
            props.append(("query", "Cam5", i, "segments", b, x, y, x + bw, y + bh))
    return pair_tables(rows, pairs, props)


def _kernels(frames: pd.DataFrame, props: pd.DataFrame, lc: LocalConfig) -> float:
    """ms per frame of the stage's kernels alone, on the sizes it works on.

    Two reduced JPEG decodes (``IMREAD_REDUCED_GRAYSCALE_4``: 404 x 308 for ``work_side`` 400),
    ORB keypoints of both at the alignment's level (``align_side``) and their matching (the
    homography's features), the gradient images,
    and every ``cv2.matchTemplate`` call both ways at the pyramid level each box is matched on.
    """
    t0 = time.perf_counter()
    n = frames["utime"].nunique()
    orb = cv2.ORB_create(nfeatures=lc.max_keypoints)  # type: ignore[attr-defined]
    for i in range(n):
        paths = frames.loc[frames["utime"] == i, "image"].tolist()
        imgs = [cv2.imread(p, cv2.IMREAD_REDUCED_GRAYSCALE_4) for p in paths]
        small = list(imgs)
        while max(small[0].shape) > lc.align_side:  # alignment's pyramid level
            small = [cv2.pyrDown(g) for g in small]
        feats = [orb.detectAndCompute(g, None) for g in small]
        if feats[0][1] is not None and feats[1][1] is not None:
            cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(feats[0][1], feats[1][1], k=2)
        levels = [[feature_image(g, lc.image) for g in imgs]]
        h, w = levels[0][0].shape
        for r in props[props["utime"] == i].itertuples():
            b = np.array([r.x1, r.y1, r.x2, r.y2], np.float64) / 4
            side, k = min(b[2] - b[0], b[3] - b[1]), 0
            while side / 2**k > lc.max_template_px:
                k += 1
                if k == len(levels):
                    levels.append([cv2.pyrDown(f) for f in levels[-1]])
            f = levels[k]
            lh, lw = f[0].shape
            x1, y1, x2, y2 = (round(v / 2**k) for v in b)
            t = max(lc.min_tolerance_px, round(lc.tolerance * np.hypot(w, h) / 2**k))
            g = max(lc.min_grow_px, round(lc.grow * max(x2 - x1, y2 - y1)), t)
            win = (slice(max(0, y1 - g), min(lh, y2 + g)), slice(max(0, x1 - g), min(lw, x2 + g)))
            for a, c in ((0, 1), (1, 0)):
                cv2.matchTemplate(f[c][win], f[a][y1:y2, x1:x2], cv2.TM_CCOEFF_NORMED)
    return 1000 * (time.perf_counter() - t0) / n


def case_local(quick: bool) -> None:
    n = 8 if quick else 32
    lc = LocalConfig()
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        frames, pairs, props = _frames(root, n)
        runs, limits = [], []
        for rep in range(3):
            t0 = time.perf_counter()
            counts = write_local_ranks(lc, pairs, frames, props, root / f"out{rep}")
            runs.append(1000 * (time.perf_counter() - t0) / n)
            limits.append(_kernels(frames, props, lc) / 2)  # the stage runs pairs on 2 threads
    med, lim = float(np.median(runs)), float(np.median(limits))
    emit(
        f"local localizer per NCLT-sized query frame [{n} pairs x {BOXES} boxes, 2 threads]",
        runs,
        "ms/frame",
        kernel_limit_ms=round(lim, 2),
        ratio_to_kernels=round(med / lim, 2),
        paper_ms_per_image=PAPER_MS,
        ratio_to_paper=round(med / PAPER_MS, 2),
        ranked=counts["ranked"],
        notes=(
            f"reduced decode + alignment ({'/'.join(lc.align)}) + matching both ways + rank "
            f"rows {med:.1f} ms/frame = {med / PAPER_MS:.2f}x the paper's {PAPER_MS} ms and "
            f"{med / lim:.2f}x its kernels' limit measured here ({lim:.1f} ms: two reduced JPEG "
            "decodes, ORB keypoints and matching, and the same matchTemplate calls, split over "
            "2 threads)"
        ),
    )

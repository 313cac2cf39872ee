"""Bench case ``keypoints``: keypoint localization per query frame, on 2 cores.

Pairs of 640 x 480 JPEG frames (a textured scene, and the same scene moved a few pixels with
objects pasted in), 80 boxes a frame (the order of ``segments``' colour regions), through
:func:`harness.localizers.keypoints.write_keypoint_ranks` with the default options (decode, SIFT
keypoints of both frames, ratio-test matches both ways, the MAGSAC fundamental matrix, the share
map, the rank rows written), beside the plain difference of the same pairs (registration,
difference map and the colours' novelty, Table D's row) and Selective Search on the query frame
(at the default's working width and the two narrower candidates of `docs/decisions.md`).
Next to them, in the same run, the limits of the stage's kernels at the sizes it works on:
decoding both frames, SIFT on both and their brute-force matching, split over the 2 threads the
stage runs pairs on. The lines: at most 100 ms a 640 x 480 pair, and at most 2x its kernels'
limit. The NCLT frame size (1,232 x 1,616, worked on at 512 px) is measured too.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from harness.config.detect import DifferenceConfig
from harness.detect.difference import difference_map, novelty_of, register
from harness.localizers.config import KeypointConfig
from harness.localizers.keypoints import detect, ratio_matches, work_gray, write_keypoint_ranks
from harness.proposals.builtin import selective_boxes
from harness.proposals.config import SelectiveConfig

from .common import emit, pair_tables

BOXES = 80
#: Selective Search's narrower working widths, timed beside the default's (``work_width``).
NARROWER = (192, 128)


def _frames(root: Path, n: int, w: int, h: int) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(0)
    rows, pairs, props = [], [], []
    for i in range(n):
        m = np.full((h, w, 3), 110, np.uint8)
        for _ in range(400):
            c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.circle(
                m,
                c,
                int(rng.integers(2, w // 40)),
                tuple(int(v) for v in rng.integers(0, 256, 3)),
                -1,
            )
        q = np.roll(m, (6, 9), axis=(0, 1)).copy()
        for _ in range(3):
            x, y = int(rng.integers(0, w - w // 5)), int(rng.integers(0, h - h // 5))
            q[y : y + h // 6, x : x + w // 8] = rng.integers(0, 256, (h // 6, w // 8, 3))
        for s, img in (("map", m), ("query", q)):
            path = root / f"{s}{i}.jpg"
            cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
            rows.append((s, "Cam5", i, str(path), w, h))
        pairs.append(("query", "Cam5", i, "map", "Cam5", i, "SP-WI"))
        for b in range(BOXES):
            bw, bh = int(rng.integers(w // 20, w // 3)), int(rng.integers(h // 20, h // 3))
            x, y = int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh))
            props.append(("query", "Cam5", i, "segments", b, x, y, x + bw, y + bh))
    return pair_tables(rows, pairs, props)


def _kernels(frames: pd.DataFrame, kc: KeypointConfig) -> float:
    """ms a pair of the kernels alone: both frames decoded to their work size, SIFT on both, the
    matching both ways; halved (the stage runs two pairs at once on 2 cores)."""
    n = frames["utime"].nunique()
    t0 = time.perf_counter()
    for i in range(n):
        f = frames[frames["utime"] == i]
        grays = [work_gray(str(r.image), int(r.width), int(r.height), kc.work_side)[0]
                 for r in f.itertuples()]  # fmt: skip
        (_, a), (_, b) = (detect(g, kc) for g in grays)
        ratio_matches(a, b, kc)
        ratio_matches(b, a, kc)
    return 1000 * (time.perf_counter() - t0) / n / 2


def _one_size(n: int, w: int, h: int, label: str) -> None:
    kc = KeypointConfig()
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        frames, pairs, props = _frames(root, n, w, h)
        runs, limits, diffs, ss = [], [], [], []
        narrower: dict[int, list[float]] = {w: [] for w in NARROWER}
        for rep in range(3):
            t0 = time.perf_counter()
            counts = write_keypoint_ranks(kc, pairs, frames, props, root / f"out{rep}")
            runs.append(1000 * (time.perf_counter() - t0) / n)
            limits.append(_kernels(frames, kc))
            imgs = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in frames["image"]]
            t0 = time.perf_counter()
            dc = DifferenceConfig()
            for i in range(0, len(imgs), 2):
                reg = register(imgs[i + 1], imgs[i], kc, dc)
                difference_map(imgs[i + 1], imgs[i], reg, dc)
                novelty_of(imgs[i + 1], imgs[i], dc)
            diffs.append(1000 * (time.perf_counter() - t0) / n)
            t0 = time.perf_counter()
            for i in range(1, len(imgs), 2):
                selective_boxes(imgs[i], SelectiveConfig())
            ss.append(1000 * (time.perf_counter() - t0) / n)
            for width, got in narrower.items():  # the candidates of docs/decisions.md
                cfg = dataclasses.replace(SelectiveConfig(), work_width=width)
                t0 = time.perf_counter()
                for i in range(1, len(imgs), 2):
                    selective_boxes(imgs[i], cfg)
                got.append(1000 * (time.perf_counter() - t0) / n)
    med, lim = float(np.median(runs)), float(np.median(limits))
    _default_row(label, n, runs, limits, diffs, ss)
    emit(
        f"keypoint localization per {label} pair [{n} pairs x {BOXES} boxes, 2 threads]",
        runs,
        "ms/pair",
        kernel_limit_ms=round(lim, 2),
        ratio_to_kernels=round(med / lim, 2),
        plain_difference_ms=round(float(np.median(diffs)), 2),
        selective_search_ms=round(float(np.median(ss)), 2),
        selective_search_ms_by_width={
            SelectiveConfig().work_width: round(float(np.median(ss)), 2),
            **{w: round(float(np.median(v)), 2) for w, v in narrower.items()},
        },
        ranked=counts["ranked"],
        notes=(
            f"decode + SIFT both frames + ratio matches both ways + MAGSAC fundamental matrix + "
            f"share map + rank rows {med:.1f} ms a pair = {med / lim:.2f}x its kernels' limit "
            f"measured here ({lim:.1f} ms: decode, SIFT on both frames and the matching, split "
            f"over 2 threads); the plain difference (registration, map, colour novelty) "
            f"{np.median(diffs):.1f} ms and Selective Search {np.median(ss):.1f} ms a frame on "
            "one thread ("
            + ", ".join(f"{np.median(v):.1f} ms {w} px wide" for w, v in narrower.items())
            + ")"
        ),
    )


def _default_row(label: str, n: int, runs: list, limits: list, diffs: list, ss: list) -> None:
    """``harness detect``'s default per pair: the three stages above together, beside their
    kernels (the keypoint stage's, and Selective Search, itself one OpenCV call)."""
    total = [a + b + c for a, b, c in zip(runs, diffs, ss, strict=True)]
    lim = [a + c for a, c in zip(limits, ss, strict=True)]
    med, lm = float(np.median(total)), float(np.median(lim))
    emit(
        f"harness detect's default per {label} pair [{n} pairs]",
        total,
        "ms/pair",
        kernel_limit_ms=round(lm, 2),
        ratio_to_kernels=round(med / lm, 2),
        line_ms=200,
        notes=(
            f"keypoint localization + registration and plain difference + Selective Search "
            f"{med:.1f} ms a pair against the line of 200 ms, {med / lm:.2f}x its kernels "
            f"({lm:.1f} ms: the keypoint stage's decode, SIFT and matching over 2 threads, and "
            "Selective Search); registration runs SIFT on both frames again"
        ),
    )


def case_keypoints(quick: bool) -> None:
    _one_size(6 if quick else 24, 640, 480, "640 x 480")
    _one_size(4 if quick else 12, 1232, 1616, "NCLT-sized (1,232 x 1,616)")

"""Bench case ``keypoints``: keypoint localization per query frame, on 2 cores.

Pairs of 640 x 480 JPEG frames (a textured scene, and the same scene moved a few pixels with
objects pasted in), 80 boxes a frame (the order of ``segments``' colour regions), through
:func:`harness.localizers.keypoints.write_keypoint_ranks` with the default options (decode, SIFT
keypoints of both frames, ratio-test matches both ways, the MAGSAC fundamental matrix, the share
map, the rank rows written), beside the plain difference of the same pairs (registration,
difference map and the colours' novelty, Table D's row; a pair a thread, a thread per core, as
``harness detect`` makes them) and the proposals stage on the query frames
(:func:`harness.proposals.proposers.compute_proposals` with Selective Search, each frame in one of
the worker processes, at the default's working width and the other candidates of
`docs/decisions.md`). The three together are the default detector's row.
Next to them, in the same run, the limits of the stages' kernels at the sizes they work on:
decoding both frames, SIFT on both and their brute-force matching, split over the 2 threads the
stage runs pairs on, and Selective Search on one thread, split over 2 processes.
The lines: at most 100 ms a 640 x 480 pair for keypoint localization, at most 2x its kernels'
limit; the default detector at most 200 ms a pair and 1.5x its kernels. The NCLT frame size
(1,232 x 1,616, worked on at 512 px) is measured too.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from harness.detect.config import DetectConfig
from harness.detect.pair import PairDifference
from harness.detect.plain import forget_root_sift
from harness.imagestore import read_image
from harness.localizers.config import KeypointConfig
from harness.localizers.keypoints import detect, ratio_matches, work_gray, write_keypoint_ranks
from harness.proposals.builtin import selective_boxes
from harness.proposals.config import ProposalsConfig, SelectiveConfig
from harness.proposals.proposers import compute_proposals, decode_scale, start_workers

from .common import emit, pair_tables

BOXES = 80
#: Selective Search's candidate working widths, each timed beside the default's (``work_width``).
WIDTHS = (256, 192, 128)


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


def _sides(frames: pd.DataFrame) -> tuple[list[str], list[str]]:
    """The query and map images of the pairs, in the pairs' order."""
    by = {
        s: g.sort_values("utime")["image"].astype(str).tolist()
        for s, g in frames.groupby("session")
    }
    return by["query"], by["map"]


def _difference_ms(frames: pd.DataFrame, kc: KeypointConfig) -> float:
    """ms a pair of the registration and plain difference (the default recipe's change map, or its
    colours' novelty where a pair is not registered) as ``harness detect`` makes them: both images
    read, one pair a thread, a thread per core."""
    opt = DetectConfig(keypoints=kc)
    queries, maps = _sides(frames)
    forget_root_sift()  # every frame detected anew, as a new pair's are

    def one(i: int) -> None:
        q, m = read_image(queries[i]), read_image(maps[i])
        PairDifference(q, m, opt)

    t0 = time.perf_counter()
    with ThreadPoolExecutor(len(os.sched_getaffinity(0))) as pool:
        list(pool.map(one, range(len(queries))))
    return 1000 * (time.perf_counter() - t0) / len(queries)


def _search_config(width: int) -> ProposalsConfig:
    return ProposalsConfig(
        methods=("selective",), selective=dataclasses.replace(SelectiveConfig(), work_width=width)
    )


def _proposals_ms(queries: pd.DataFrame, width: int) -> float:
    """ms a frame of ``harness detect``'s proposals stage with Selective Search ``width`` wide:
    :func:`compute_proposals`, each frame read at its reduced scale and searched in one of the
    worker processes (one per core, started ahead, as a run starts them)."""
    t0 = time.perf_counter()
    compute_proposals(queries, _search_config(width))
    return 1000 * (time.perf_counter() - t0) / len(queries)


def _search_kernel_ms(queries: pd.DataFrame) -> float:
    """ms a frame of Selective Search on one thread in this process, at the default's width
    (:func:`selective_boxes`: its OpenCV call on the working copy, the area limits and NMS; the
    frame read at its reduced scale outside the clock)."""
    cfg = _search_config(SelectiveConfig().work_width)
    images = [read_image(f.image, decode_scale(int(f.width), cfg, ["selective"], False))
              for f in queries.itertuples()]  # fmt: skip
    t0 = time.perf_counter()
    for im in images:
        selective_boxes(im, cfg.selective)
    return 1000 * (time.perf_counter() - t0) / len(images)


def _one_size(n: int, w: int, h: int, label: str) -> None:
    kc = KeypointConfig()
    default = SelectiveConfig().work_width
    widths = (default, *(x for x in WIDTHS if x != default))
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        frames, pairs, props = _frames(root, n, w, h)
        queries = frames[frames["session"] == "query"].reset_index(drop=True)
        start_workers(_search_config(widths[0]), ["selective"])  # as a run does, ahead
        compute_proposals(queries, _search_config(widths[0]))  # the workers warm, not timed
        runs, limits, diffs, kernel = [], [], [], []
        search: dict[int, list[float]] = {width: [] for width in widths}
        for rep in range(3):
            t0 = time.perf_counter()
            counts = write_keypoint_ranks(kc, pairs, frames, props, root / f"out{rep}")
            runs.append(1000 * (time.perf_counter() - t0) / n)
            limits.append(_kernels(frames, kc))
            diffs.append(_difference_ms(frames, kc))
            for width, got in search.items():  # the default's, then docs/decisions.md's candidates
                got.append(_proposals_ms(queries, width))
            kernel.append(_search_kernel_ms(queries))
    med, lim = float(np.median(runs)), float(np.median(limits))
    _default_row(label, n, runs, limits, diffs, search[widths[0]], kernel)
    by_width = {width: round(float(np.median(v)), 2) for width, v in search.items()}
    rest = med + float(np.median(diffs))
    emit(
        f"keypoint localization per {label} pair [{n} pairs x {BOXES} boxes, 2 threads]",
        runs,
        "ms/pair",
        kernel_limit_ms=round(lim, 2),
        ratio_to_kernels=round(med / lim, 2),
        plain_difference_ms=round(float(np.median(diffs)), 2),
        selective_search_ms=by_width[widths[0]],
        selective_search_ms_by_width=by_width,
        selective_search_kernel_ms=round(float(np.median(kernel)), 2),
        pair_ms_by_width={width: round(rest + v, 1) for width, v in by_width.items()},
        ranked=counts["ranked"],
        notes=(
            f"decode + SIFT both frames + ratio matches both ways + MAGSAC fundamental matrix + "
            f"share map + rank rows {med:.1f} ms a pair = {med / lim:.2f}x its kernels' limit "
            f"measured here ({lim:.1f} ms: decode, SIFT on both frames and the matching, split "
            f"over 2 threads); the plain difference (registration, change map or colours, a pair a "
            f"thread) {np.median(diffs):.1f} ms and the proposals stage (Selective Search in a "
            f"worker process per core) {by_width[widths[0]]:.1f} ms a frame, on one thread in "
            f"this process {np.median(kernel):.1f} ms; at the other widths the stage "
            + ", ".join(f"{by_width[x]:.1f} ms {x} px wide" for x in widths[1:])
            + ", a pair then "
            + ", ".join(f"{rest + by_width[x]:.1f} ms" for x in widths[1:])
        ),
    )


def _default_row(
    label: str, n: int, runs: list, limits: list, diffs: list, search: list, kernel: list
) -> None:
    """``harness detect``'s default per pair: the three stages above, each as a run makes it on
    this machine's cores, together; beside their kernels (the keypoint stage's over 2 threads,
    and Selective Search on one thread, split over the 2 worker processes)."""
    total = [a + b + c for a, b, c in zip(runs, diffs, search, strict=True)]
    lim = [a + c / 2 for a, c in zip(limits, kernel, strict=True)]
    med, lm = float(np.median(total)), float(np.median(lim))
    emit(
        f"harness detect's default per {label} pair [{n} pairs]",
        total,
        "ms/pair",
        kernel_limit_ms=round(lm, 2),
        ratio_to_kernels=round(med / lm, 2),
        line_ms=200,
        notes=(
            f"keypoint localization + registration and plain difference + the proposals stage "
            f"(Selective Search) {med:.1f} ms a pair against the line of 200 ms, {med / lm:.2f}x "
            f"its kernels ({lm:.1f} ms: the keypoint stage's decode, SIFT and matching over 2 "
            "threads, and Selective Search on one thread, halved); registration runs SIFT on "
            "both frames again"
        ),
    )


def case_keypoints(quick: bool) -> None:
    _one_size(6 if quick else 24, 640, 480, "640 x 480")
    _one_size(4 if quick else 12, 1232, 1616, "NCLT-sized (1,232 x 1,616)")

"""Fused samples (method §7): every query image's fused boxes with their LoC.

Each image's proposals and ranks become fused sets (:func:`harness.fusion.fuse.fuse`), one row a
box and method. Labels are the caller's (:class:`Labels`; the benchmark's samples stage builds them
from the annotations in :mod:`harness.fusion.stage`): ``harness detect`` fuses unlabelled and so
never imports the evaluation's labelling.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from harness.fusion.config import FusionConfig
from harness.fusion.fuse import (
    IMAGE_BASELINES,
    cover_matrix,
    image_loc,
    intersection_closure,
    loc_from_cover,
    rows_of,
)
from harness.methods import (
    is_unfused,
    ordered_methods,
    unfused,
)
from harness.records import FRAME_KEY, IMAGE_KEY
from harness.runtime.cache import stable_hash

#: The columns of a sample table before the LoC of each method (``loc_<method>``).
SAMPLE_COLUMNS = (
    *IMAGE_KEY,
    "season_pair",
    "proposal_method",
    *("x1", "y1", "x2", "y2", "original", "N", "RoC", "SoB"),
)


@dataclass(frozen=True)
class Labels:
    """What labels the samples: the annotated frames' change boxes and the RoC/SoB rule.

    ``changes``: frame key -> (c, 4) change boxes (c = 0 for a no-change frame); ``roc_sob``:
    ``(boxes, change_boxes, width, height) -> (roc, sob)`` (method §8).
    """

    changes: Mapping[tuple[str, str, int], np.ndarray]
    roc_sob: Callable[[np.ndarray, np.ndarray, float, float], tuple[np.ndarray, np.ndarray]]


def _runs(kcols: list[np.ndarray], n: int) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) of each run of equal keys in the sorted key columns ``kcols``."""
    change = np.zeros(n, bool)
    for kc in kcols:
        change[1:] |= kc[1:] != kc[:-1]
    starts = np.concatenate([[0], np.nonzero(change)[0]]) if n else np.zeros(0, np.int64)
    return starts, np.append(starts[1:], n)


def _fuse_image(
    boxes: np.ndarray,
    rdl: tuple[np.ndarray, np.ndarray, np.ndarray],
    image: tuple[tuple[Any, Any], np.ndarray | None, int],
    rules: tuple[tuple[str, ...], int, float, dict[str, Any]],
    counts: dict[str, Any],
    labels: Labels | None = None,
) -> dict[str, np.ndarray]:
    """The sample columns of one query image and proposal set, from its boxes' ``r, d, L``.

    ``image``: its size, its change boxes and its seed; ``rules``: the fusion rules, the most
    fused boxes, RRF's constant and each rule's registered options. Rows: the fused boxes, then
    the duplicate originals. Columns: the box, ``original``, ``N``, ``RoC``, ``SoB`` and
    ``loc_<method>`` per method.
    """
    r, d, L = rdl
    (w, h), change, img_seed = image
    methods, max_boxes, rrf_c, options = rules
    fused, capped = intersection_closure(boxes, max_boxes)
    counts["capped_closures"] += int(capped)
    cover = cover_matrix(fused, boxes)
    locs = {}
    for m in methods:
        if m in IMAGE_BASELINES:
            locs[m] = image_loc(fused, m, w, h, img_seed)
        elif not is_unfused(m):
            locs[m] = loc_from_cover(
                cover, m, r=r, d=d, L=L, seed=img_seed, rrf_c=rrf_c, options=options[m]
            )
    # rank_no_fusion: one sample per original box; merged into the fused row of the same box
    nof = np.full(len(fused), np.nan)
    extra = []
    for k, i in enumerate(rows_of(fused, boxes).tolist()):
        if np.isnan(nof[i]):
            nof[i] = r[k]
        else:
            extra.append((tuple(boxes[k]), r[k]))
    all_boxes = np.vstack([fused, np.array([bx for bx, _ in extra]).reshape(-1, 4)])
    if change is None or labels is None:  # unlabelled: no RoC; SoB is the box's share of the frame
        area = (all_boxes[:, 2] - all_boxes[:, 0]) * (all_boxes[:, 3] - all_boxes[:, 1])
        roc, sob = np.full(len(all_boxes), np.nan), area / float(w * h)
    else:
        roc, sob = labels.roc_sob(all_boxes, change, w, h)
    n_x = len(extra)
    part = {c: all_boxes[:, j] for j, c in enumerate(("x1", "y1", "x2", "y2"))}
    part["original"] = np.concatenate([~np.isnan(nof), np.ones(n_x, bool)])
    part["N"] = np.concatenate([cover.sum(1), np.ones(n_x, np.int64)]).astype(np.int64)
    part["RoC"] = np.asarray(roc, np.float64)
    part["SoB"] = np.asarray(sob, np.float64)
    nf = unfused(methods)
    if nf is not None:
        part[f"loc_{nf}"] = np.concatenate([nof, [v for _, v in extra]])
    for m, v in locs.items():
        part[f"loc_{m}"] = np.concatenate([v, np.full(n_x, np.nan)])
    return part


def _fusion_jobs(
    kcols: list[np.ndarray],
    proposer: np.ndarray,
    runs: tuple[np.ndarray, np.ndarray],
    subsets: list[tuple[str, list[str]]],
    cb: Any,
    counts: dict[str, Any],
) -> list[tuple[Any, ...]]:
    """(image key, subset name, its rows, its first row) of each image and subset to fuse.

    In the images' order; images without labels (``cb``) are left out; ``counts`` counts the rest.
    """
    jobs = []
    for a, b in zip(*runs, strict=True):
        key = (str(kcols[0][a]), str(kcols[1][a]), int(kcols[2][a]), str(kcols[3][a]))
        if cb is not None and key[:3] not in cb:
            continue
        counts["query_images"] += 1
        for name, ms in subsets:
            sel = np.isin(proposer[a:b], ms)
            if sel.any():
                jobs.append((key, name, np.flatnonzero(sel) + a, a))
    return jobs


def fuse_samples(
    ranks: pd.DataFrame,
    frames: pd.DataFrame,
    labels: Labels | None,
    fusion: FusionConfig,
    progress: Callable[[Iterable[Any]], Iterable[Any]] = lambda it: it,
    threads: int = 1,
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Samples of every labelled query image (one per pair) with the LoC of each method.

    ``labels`` None: every query image of ``ranks``, unlabelled (``RoC`` NaN; ``harness detect``).
    ``fusion`` gives the methods (any order: the method's is kept), the seed, the cap on fused boxes
    per image, RRF's constant and a registered rule's options.

    Samples are built for all proposal methods together (``proposals = all``) and, where there
    are several, for each alone. Columns: the query image's key, ``season_pair``, ``proposals``,
    the box, ``original`` (an original box rather than only an intersection), ``N``, ``RoC``,
    ``SoB`` and ``loc_<method>`` for each of ``methods``. ``rank_no_fusion`` has values on
    original boxes only (an original box that is also another's fused box shares its row; a
    duplicate original gets a row of its own), the fused-set methods on fused boxes only.

    Numpy columns of ``ranks`` sorted once (stable) by query image; one table built at the end.
    ``threads``: images fused side by side (numpy releases the GIL), gathered in their order: the
    same table whatever the count.
    """
    cb = labels.changes if labels is not None else None
    wh = frames[["width", "height"]].to_numpy()
    size = dict(zip(frames[FRAME_KEY].itertuples(index=False, name=None), wh, strict=True))
    counts = {"query_images": 0, "capped_closures": 0}
    seed, max_boxes = fusion.seed, fusion.max_fused_boxes
    methods = ordered_methods(fusion.methods)
    options = {m: fusion.options_of(m) for m in methods}
    rules_of = (methods, max_boxes, fusion.rrf_c, options)
    props = sorted(ranks["proposal_method"].unique())
    subsets = [("all", props)] + ([(m, [m]) for m in props] if len(props) > 1 else [])
    srt = ranks.sort_values(list(IMAGE_KEY), kind="stable")
    kcols = [srt[k].to_numpy() for k in IMAGE_KEY]
    season_pair = srt["season_pair"].to_numpy()
    box_all = srt[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    r_all, d_all = srt["r"].to_numpy(np.float64), srt["d"].to_numpy(np.float64)
    L_all = srt["L"].to_numpy(np.float64)
    starts, ends = _runs(kcols, len(srt))
    cols: dict[str, list[Any]] = {c: [] for c in (*SAMPLE_COLUMNS, *(f"loc_{m}" for m in methods))}
    jobs = _fusion_jobs(
        kcols, srt["proposal_method"].to_numpy(), (starts, ends), subsets, cb, counts
    )

    def fuse(job: tuple[Any, ...]) -> tuple[dict[str, np.ndarray], int]:
        key, name, rows, _ = job
        mine = {"capped_closures": 0}
        image = (tuple(size[key[:3]]), cb[key[:3]] if cb is not None else None,
                 int(stable_hash(seed, key, name, length=8), 16))  # fmt: skip
        rdl = (r_all[rows], d_all[rows], L_all[rows])
        part = _fuse_image(box_all[rows], rdl, image, rules_of, mine, labels)
        return part, mine["capped_closures"]

    with ThreadPoolExecutor(max(1, threads), thread_name_prefix="fusion") as pool:
        done = [pool.submit(fuse, job) for job in jobs]
        for job, fut in zip(progress(jobs), done, strict=True):
            key, name, _, a = job
            part, capped = fut.result()
            counts["capped_closures"] += capped
            n_rows = len(part["x1"])
            for c, v in zip(IMAGE_KEY, key, strict=True):
                cols[c].append(np.full(n_rows, v, dtype=np.int64 if c == "q_utime" else object))
            cols["season_pair"].append(np.full(n_rows, season_pair[a], dtype=object))
            cols["proposal_method"].append(np.full(n_rows, name, dtype=object))
            for c, v in part.items():
                cols[c].append(v)
    if not cols["x1"]:
        return pd.DataFrame(), counts
    df = pd.DataFrame({c: np.concatenate(v) for c, v in cols.items()})
    return df, counts

"""The ``local`` localizer (method §13.3): each subimage ranked inside its paired map frame.

The robot knows where it is: the pair names the map frame a query frame should look like. What
it asks here is whether each *part* of its view still localizes where it should, the fine stage
of a hierarchical localizer one level below the paper's retrieval:

1. :func:`harness.localizers.align.align_pair` aligns the map frame to the query frame: a
   homography from ORB (or SIFT) matches with RANSAC, accepted only with enough inliers and a
   plausible warp; else an affine ECC fit; else identity where the two frames still overlap;
   else the pair is *not aligned* and its subimages get no rank (counted).
2. :func:`box_rank`: a subimage's gradient-magnitude crop is matched (``cv2.matchTemplate``,
   ``TM_CCOEFF_NORMED``) over a window of the warped map frame around its own position (the box
   grown by ``grow`` of its size on each side, at least ``min_grow_px``); its ``rank`` is one plus
   the number of window positions that match better than the best position within the tolerance
   (``tolerance`` of the box's shorter side, at least ``min_tolerance_px``) of the expected one,
   ``L`` the number of window positions, ``r = rank / L`` as every localizer's (method §6).
3. The same from map to query (a removed object exists only in the map frame); the subimage
   keeps the worse (larger) ``r``.

Work happens at the resolution the boxes need: frames whose longer side exceeds ``work_side``
are decoded reduced (a JPEG at 1/2, 1/4 or 1/8 of its size, :func:`harness.imagestore.read_image`)
and the boxes scaled with them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.imagestore import ImageRef, read_image
from harness.localizers.align import Alignment, align_pair, feature_image
from harness.localizers.config import LocalConfig
from harness.records import FRAME_KEY, IMAGE_KEY
from harness.runtime.cache import write_parquet

__all__ = [
    "box_rank",
    "pair_images",
    "pair_ranks",
    "read_gray",
    "unit_ranks",
    "work_image",
    "write_local_ranks",
]


def _rank_in(
    src: np.ndarray, dst: np.ndarray, valid: np.ndarray, box: tuple[int, int, int, int],
    lc: LocalConfig, diagonal: float,
) -> tuple[int, int, float] | None:  # fmt: skip
    """``valid``: the integral image (``cv2.integral``) of where the warped map has pixels."""
    # (rank, L, best NCC) of src's patch box searched in dst around the same place
    x1, y1, x2, y2 = box
    tw, th = x2 - x1, y2 - y1
    h, w = dst.shape[:2]
    t = max(lc.min_tolerance_px, round(lc.tolerance * diagonal))
    g = max(lc.min_grow_px, round(lc.grow * max(tw, th)), lc.window_over_tolerance * t)
    wx0, wy0, wx1, wy1 = max(0, x1 - g), max(0, y1 - g), min(w, x2 + g), min(h, y2 + g)
    if wx1 - wx0 <= tw or wy1 - wy0 <= th:
        return None
    inside = int(valid[y2, x2]) - int(valid[y1, x2]) - int(valid[y2, x1]) + int(valid[y1, x1])
    if inside / float(tw * th) < 0.9:  # the expected place is outside the other frame
        return None
    res = cv2.matchTemplate(dst[wy0:wy1, wx0:wx1], src[y1:y2, x1:x2], cv2.TM_CCOEFF_NORMED)
    ex, ey = x1 - wx0, y1 - wy0  # the expected position in the response
    best = cv2.minMaxLoc(res[max(0, ey - t) : ey + t + 1, max(0, ex - t) : ex + t + 1])[1]
    return int(np.count_nonzero(res > best)) + 1, int(res.size), best


def box_rank(
    q: np.ndarray, m: np.ndarray, valid: np.ndarray, box: tuple[int, int, int, int],
    lc: LocalConfig, diagonal: float | None = None,
) -> tuple[int, int, float] | None:  # fmt: skip
    """:func:`_box_rank` with ``valid`` a boolean image of where the warped map has pixels."""
    ii = cv2.integral(np.asarray(valid, np.uint8), sdepth=cv2.CV_32S)
    return _box_rank(q, m, ii, box, lc, diagonal)


def _box_rank(
    q: np.ndarray, m: np.ndarray, valid: np.ndarray, box: tuple[int, int, int, int],
    lc: LocalConfig, diagonal: float | None = None,
) -> tuple[int, int, float] | None:  # fmt: skip
    """A query box's local (rank, L, best NCC): query to map, and map to query where asked.

    ``q``: the query's feature image; ``m``: the map's, warped into the query's pixels;
    ``valid``: the integral image of where the warped map has pixels. The worse (larger) ``r``
    of the two directions is kept. None: the box is too small or its window leaves the frame
    (counted by the caller).
    ``diagonal``: the frame diagonal the tolerance is a share of, in these pixels (None: ``q``'s).
    """
    diagonal = math.hypot(*q.shape[:2]) if diagonal is None else diagonal
    x1, y1, x2, y2 = box
    if x2 - x1 < 2 or y2 - y1 < 2:
        return None
    fwd = _rank_in(q, m, valid, box, lc, diagonal)
    if fwd is None or not lc.both_directions:
        return fwd
    back = _rank_in(m, q, valid, box, lc, diagonal)
    if back is None:
        return fwd
    return fwd if fwd[0] / fwd[1] >= back[0] / back[1] else back


def work_image(uri: str, width: int, height: int, work_side: int) -> tuple[np.ndarray, float]:
    """A frame's gray work image and its scale (work pixels per frame pixel)."""
    reduce = 1
    while reduce < 8 and max(width, height) / (reduce * 2) >= work_side:
        reduce *= 2
    gray = read_gray(uri, reduce) if reduce > 1 else None
    if gray is None:
        gray = cv2.cvtColor(read_image(uri, reduce), cv2.COLOR_RGB2GRAY)
    return gray, gray.shape[1] / float(width)


def read_gray(uri: str, reduce: int) -> np.ndarray | None:
    """A JPEG decoded straight to gray at 1/``reduce``, upright (less work than colour).

    None for any other file: the caller decodes it in colour.
    """
    ref = ImageRef.parse(uri)
    path, rot = ref.path, ref.rotation
    if ref.perturbation is not None or not path.lower().endswith((".jpg", ".jpeg")):
        return None  # a perturbed copy is made in colour, by read_image
    flag = {2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
            8: cv2.IMREAD_REDUCED_GRAYSCALE_8}[reduce]  # fmt: skip
    gray = cv2.imread(path, flag)
    if gray is None:
        return None  # the colour path says what is wrong with the file
    turn = {"cw": cv2.ROTATE_90_CLOCKWISE, "ccw": cv2.ROTATE_90_COUNTERCLOCKWISE,
            "180": cv2.ROTATE_180}.get(rot)  # fmt: skip
    return np.ascontiguousarray(cv2.rotate(gray, turn) if turn is not None else gray)


def pair_images(
    q_uri: str,
    m_uri: str,
    size: tuple[int, int],
    side: int,
    work: Callable[[str, int, int, int], tuple[np.ndarray, float]],
) -> tuple[np.ndarray, np.ndarray, float]:
    """A pair's gray work images by ``work``, and the query's scale (work pixels a frame pixel).

    The map's is resized to the query's where they differ; ``size``: the frames' (width, height).
    """
    q, s = work(q_uri, *size, side)
    m, _ = work(m_uri, *size, side)
    if m.shape != q.shape:
        m = cv2.resize(m, (q.shape[1], q.shape[0]), interpolation=cv2.INTER_AREA)
    return q, m, s


def pair_ranks(
    q_uri: str, m_uri: str, size: tuple[int, int], boxes: np.ndarray, lc: LocalConfig
) -> tuple[Alignment, np.ndarray]:
    """One pair's alignment and each query box's (rank, L, best NCC), NaN rows where none.

    ``size``: the frames' (width, height); ``boxes``: (n, 4) in frame pixels.
    """
    q, m, s = pair_images(q_uri, m_uri, size, lc.work_side, work_image)
    al = align_pair(q, m, lc)
    out = np.full((len(boxes), 3), np.nan)
    if al.H is None:
        return al, out
    fq, fm = feature_image(q, lc.image), feature_image(m, lc.image)
    h, w = q.shape
    Hs = al.H  # the alignment ran on the work images: H is in work pixels
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped = cv2.warpPerspective(fm, Hs, (w, h), flags=flags, borderValue=0)
    valid = cv2.warpPerspective(np.ones_like(q), Hs, (w, h), flags=flags, borderValue=0) > 0
    levels = [(fq, warped, valid)]
    integrals = [cv2.integral(valid.astype(np.uint8), sdepth=cv2.CV_32S)]
    b = np.asarray(boxes, np.float64).reshape(-1, 4) * s
    k = _levels(np.minimum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]), (h, w), lc.max_template_px)
    at = np.round(b / np.exp2(k)[:, None])  # half to even, as round() is
    for i, (ki, (x1, y1, x2, y2)) in enumerate(zip(k.tolist(), at.tolist(), strict=True)):
        while ki >= len(levels):  # the next pyramid level, built once per pair
            a, m_, v = levels[-1]
            levels.append((cv2.pyrDown(a), cv2.pyrDown(m_), cv2.pyrDown(v.astype(
                np.float32)) > 0.99))  # fmt: skip
            integrals.append(cv2.integral(levels[-1][2].astype(np.uint8), sdepth=cv2.CV_32S))
        lq, lm, _ = levels[ki]
        lh, lw = lq.shape
        box = (min(max(int(x1), 0), lw), min(max(int(y1), 0), lh), min(max(int(x2), 0), lw),
               min(max(int(y2), 0), lh))  # fmt: skip
        got = _box_rank(lq, lm, integrals[ki], box, lc, math.hypot(w, h) / 2**ki)
        if got is not None:
            out[i] = got
    return al, out


def _levels(side: np.ndarray, shape: tuple[int, int], max_px: int) -> np.ndarray:
    """Each box's pyramid level, from its shorter ``side`` (level 0's pixels).

    Halved until the side is at most ``max_px``, but never past a level whose shorter image
    side is under 16 px (``shape``: level 0's).
    """
    k = np.zeros(len(side), np.int64)
    h, w, level = *shape, 0
    while min(h, w) >= 16:  # a box may go one level further than this one
        deeper = side / 2**level > max_px
        if not deeper.any():
            break
        k += deeper
        h, w, level = (h + 1) // 2, (w + 1) // 2, level + 1
    return k


#: ``alignment.parquet``/``alignment.csv``: the pair, then how it was aligned.
ALIGNMENT_COLUMNS = [*IMAGE_KEY, "r_camera", "r_utime", "align", "inliers", "align_score"]

#: The counters of a unit of local ranks.
LOCAL_COUNTS = (
    "query_subimages",
    "ranked",
    "no_rank_pair_not_aligned",
    "no_rank_box_too_small_or_outside",
    "pairs_homography",
    "pairs_ecc",
    "pairs_identity",
    "pairs_not_aligned",
)


def _rank_rows(
    pairs: pd.DataFrame, props: pd.DataFrame, which: np.ndarray, at: np.ndarray, g: np.ndarray
) -> pd.DataFrame:
    """The rank rows (method §6's columns) of a unit's ranked boxes, in one table.

    Row ``i`` is ``props`` row ``at[i]``, ranked in the pair of ``pairs`` row ``which[i]``, with
    its (rank, L, best NCC) ``g[i]``.
    """
    rank, L = g[:, 0].astype(np.int64), g[:, 1].astype(np.int64)
    b = props.iloc[at]
    p = pairs.iloc[which]
    return pd.DataFrame(
        {
            "q_session": p["q_session"].to_numpy(),
            "q_camera": p["q_camera"].to_numpy(),
            "q_utime": p["q_utime"].to_numpy(np.int64),
            "r_session": p["r_session"].to_numpy(),
            "r_camera": p["r_camera"].to_numpy(),
            "r_utime": p["r_utime"].to_numpy(np.int64),
            "season_pair": p["season_pair"].to_numpy(),
            "proposal_method": b["proposal_method"].to_numpy(),
            "box_id": b["box_id"].to_numpy(),
            **{c: b[c].to_numpy(np.float64) for c in ("x1", "y1", "x2", "y2")},
            "rank": rank,
            "L": L,
            "r": rank / L,
            "r_desc": (L + 1 - rank) / L,
            "d": 1.0 - g[:, 2],  # 1 - the best NCC within the tolerance
            "exact": np.ones(len(g), bool),
            "place_size": np.ones(len(g), np.int64),
        }
    )


def write_local_ranks(
    lc: LocalConfig, pairs: pd.DataFrame, frames: pd.DataFrame, props: pd.DataFrame, tmp: Path
) -> dict[str, int]:
    """One unit's rank rows (``ranks.parquet``) and alignments (``alignment.parquet``).

    ``pairs``: the unit's pairs; ``props``: the query sessions' proposals (every method).
    """

    def one(q_img: str, m_img: str, wh: tuple[int, int], xy: np.ndarray) -> tuple[tuple, Any]:
        al, got = pair_ranks(q_img, m_img, wh, xy, lc)
        return (al.method, al.inliers, al.score), (got if al.H is not None else None)

    return unit_ranks(
        one, pairs, frames, props, tmp, LOCAL_COUNTS, "no_rank_box_too_small_or_outside"
    )


#: (query image, map image, (width, height), boxes) -> ((method, inliers, score), each box's
#: (rank, L, 1 - d) or NaN, or None where the pair could not be aligned).
PairRanks = Callable[[str, str, tuple[int, int], np.ndarray], tuple[tuple, Any]]


def unit_ranks(
    pair_fn: PairRanks,
    pairs: pd.DataFrame,
    frames: pd.DataFrame,
    props: pd.DataFrame,
    tmp: Path,
    names: tuple[str, ...],
    not_ranked: str,
) -> dict[str, int]:
    """A unit of a kind that ranks each query box inside its paired map frame.

    ``local`` and ``keypoints``: its rank rows and each pair's alignment, the counters ``names``
    counted (``pairs_<method>``, ``not_ranked`` for a box without a rank).
    """
    pairs = pairs.reset_index(drop=True)
    times = np.union1d(pairs["q_utime"].to_numpy(np.int64), pairs["r_utime"].to_numpy(np.int64))
    mine = frames.loc[frames["utime"].isin(times), [*FRAME_KEY, "image", "width", "height"]]
    files = {  # a frame's (image, width, height), looked up without pandas in the worker threads
        (s, c, int(u)): (str(i), int(w), int(h))
        for s, c, u, i, w, h in mine.itertuples(index=False, name=None)
    }
    at_frame = props.groupby(FRAME_KEY, sort=False).indices
    xy = props[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    none = np.zeros(0, np.int64)

    def one(row: tuple) -> tuple[tuple, np.ndarray, Any]:
        qs, qc, qu, rs, rc, ru = row
        at = at_frame.get((qs, qc, int(qu)), none)
        q_img, w, h = files[(qs, qc, int(qu))]
        how, got = pair_fn(q_img, files[(rs, rc, int(ru))][0], (w, h), xy[at])
        return how, at, got

    keys = pairs[["q_session", "q_camera", "q_utime", "r_session", "r_camera", "r_utime"]]
    workers = max(1, min(len(pairs), os.cpu_count() or 1))
    with ThreadPoolExecutor(workers) as pool:  # OpenCV releases the GIL: pairs run side by side
        done = list(pool.map(one, keys.itertuples(index=False, name=None)))
    counts = dict.fromkeys(names, 0)
    aligns, which, ats, gots = [], [], [], []
    for i, (row, (how, at, got)) in enumerate(
        zip(pairs.itertuples(index=False), done, strict=True)
    ):
        counts["query_subimages"] += len(at)
        said = f"pairs_{how[0] if got is not None else 'not_aligned'}"
        counts[said] = counts.get(said, 0) + 1
        aligns.append(
            (row.q_session, row.q_camera, int(row.q_utime), row.r_session, row.r_camera,
             int(row.r_utime), *how)
        )  # fmt: skip
        if got is None:
            counts["no_rank_pair_not_aligned"] += len(at)
            continue
        ok = np.isfinite(got[:, 0])
        counts[not_ranked] += int((~ok).sum())
        counts["ranked"] += int(ok.sum())
        which.append(np.full(int(ok.sum()), i, np.int64))
        ats.append(at[ok])
        gots.append(got[ok])
    df = (
        _rank_rows(pairs, props, np.concatenate(which), np.concatenate(ats), np.concatenate(gots))
        if counts["ranked"]
        else pd.DataFrame()
    )
    write_parquet(tmp / "ranks.parquet", df)
    write_parquet(tmp / "alignment.parquet", pd.DataFrame(aligns, columns=ALIGNMENT_COLUMNS))
    return counts

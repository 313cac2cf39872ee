"""Table P's figures (method §13.2): each query image's LoC map scored against its change masks.

Pooled over images with a bootstrap interval and the chance floor of a random map.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np
import pandas as pd

from harness.evaluate import chance
from harness.evaluate.aps import Pooled, chance_fields, query_frames, sample_groups
from harness.evaluate.config import EvalSettings
from harness.evaluate.metrics import (
    average_precision,
    bootstrap_aps,
    weighted_average_precision,
)
from harness.ingest.annotations import change_boxes
from harness.methods import is_unfused, unfused
from harness.records import frame_sizes


def pixel_regions(
    boxes: np.ndarray, change: np.ndarray, width: float, height: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The image cut into rectangular regions by every box edge (exact areas, method §9).

    Returns:
        (area (c,), positive (c,) bool: inside the union of the change boxes, owner (c,) int: the
        index of the smallest box of ``boxes`` holding the region, -1 where none does).
        Ties in area (identical boxes) go to the lowest index; callers order boxes so that this
        is the box they want.
    """
    b = np.clip(np.asarray(boxes, np.float64).reshape(-1, 4), 0, [width, height, width, height])
    ch = np.clip(np.asarray(change, np.float64).reshape(-1, 4), 0, [width, height, width, height])
    xs = np.unique(np.concatenate([[0.0, width], b[:, 0], b[:, 2], ch[:, 0], ch[:, 2]]))
    ys = np.unique(np.concatenate([[0.0, height], b[:, 1], b[:, 3], ch[:, 1], ch[:, 3]]))
    area = np.outer(np.diff(ys), np.diff(xs))  # (rows, cols) of the region grid
    owner = np.full(area.shape, -1, np.int64)
    # paint boxes from the largest to the smallest, so each region keeps the smallest box holding it
    barea = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    order = np.lexsort((-np.arange(len(b)), -barea))  # equal areas: the lowest index painted last
    cx0, cx1 = np.searchsorted(xs, b[:, 0]), np.searchsorted(xs, b[:, 2])
    cy0, cy1 = np.searchsorted(ys, b[:, 1]), np.searchsorted(ys, b[:, 3])
    for i in order:
        owner[cy0[i] : cy1[i], cx0[i] : cx1[i]] = i
    positive = np.zeros(area.shape, bool)
    for x0, y0, x1, y1 in ch:
        positive[
            np.searchsorted(ys, y0) : np.searchsorted(ys, y1),
            np.searchsorted(xs, x0) : np.searchsorted(xs, x1),
        ] = True
    return area.ravel(), positive.ravel(), owner.ravel()


def region_scores(
    box_scores: np.ndarray, owner: np.ndarray, low: float | None = None
) -> np.ndarray:
    """(b, regions) scores of the regions of :func:`pixel_regions` from (b, boxes) box scores.

    Each region takes its owner box's score; a region no box holds (``owner`` -1), and one whose
    box has no finite score (a box that could not be scored is no box), takes ``low``: the
    lowest finite score of its row where None (0 where the row has none), as the run's lowest LoC
    for a method's own map.
    """
    s = np.atleast_2d(np.asarray(box_scores, np.float64))
    ok = np.isfinite(s)
    if low is None:
        row_low = np.where(ok, s, np.inf).min(axis=1, keepdims=True, initial=np.inf)
        floor: np.ndarray | float = np.where(np.isfinite(row_low), row_low, 0.0)
    else:
        floor = low
    s = np.where(ok, s, floor)
    if not s.shape[1]:
        return np.broadcast_to(np.asarray(floor, np.float64), (len(s), len(owner))).copy()
    return np.where(owner[None, :] >= 0, s[:, np.maximum(owner, 0)], floor)


def pixel_image_rows(
    cfg: EvalSettings,
    samples: pd.DataFrame,
    frames: pd.DataFrame,
    ann: pd.DataFrame,
    methods: tuple[str, ...],
    ids: dict[str, int],
) -> list[dict]:
    """Table P (method §9).

    Pixel AP over exact regions and image AP, pooled, with intervals.
    """
    px, img, maps = _pixel_image_scores(samples, frames, ann, methods, ids)
    chance_of = _map_chance(cfg, maps, samples["RoC"].to_numpy(np.float64))
    names = np.empty(len(ids), dtype=object)
    for k, v in ids.items():
        names[v] = k
    rows = []
    for name, data in (("pixel", px), ("image", img)):
        pooled = Pooled(cfg, ids, f"P:{name}")
        for m in methods:
            ap, g_, extra, boot = _p_ap(name, data[m])
            extra["positive_images"] = query_frames(names[g_[extra.pop("_positive_groups")]])
            floor, ceiling = chance_of[(name, "orig" if is_unfused(m) else "fused")]
            pooled.add(
                m,
                {
                    "table": "P",
                    "split": name,
                    "roc_max": float("nan"),
                    "proposal_method": "all",
                    "season_pair": "all",
                    "ap": ap,
                    **chance_fields(floor, ap, ceiling),
                    "left_out": 0,
                    "query_images": len(np.unique(g_)),
                    **extra,
                },
                boot,
            )
        rows += pooled.finish()
    return rows


def _box_sets(
    idx: np.ndarray, in_fused: np.ndarray, locs: dict[str, np.ndarray], methods: tuple[str, ...]
) -> dict[str, np.ndarray]:
    """A frame's sample rows by box set: the fused qBBs, and the original proposals by LoC."""
    sets = {"fused": idx[in_fused[idx]]}
    nf = unfused(methods)
    if nf is not None:
        o = idx[np.isfinite(locs[nf][idx])]
        sets["orig"] = o[
            np.argsort(-locs[nf][o], kind="stable")
        ]  # identical boxes: the highest LoC owns their regions
    return sets


def _merged_regions(
    boxes: np.ndarray, change: np.ndarray, w: float, h: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`pixel_regions` with the regions of one owner and label summed: (area, label, owner).

    Regions with the same owner and label get the same LoC under every method.
    """
    area, pos, owner = pixel_regions(boxes, change, w, h)
    uniq, inv = np.unique((owner + 1) * 2 + pos, return_inverse=True)
    return np.bincount(inv, weights=area), (uniq % 2).astype(bool), uniq // 2 - 1


def _pixel_image_scores(
    samples: pd.DataFrame,
    frames: pd.DataFrame,
    ann: pd.DataFrame,
    methods: tuple[str, ...],
    ids: dict[str, int],
) -> tuple[dict, dict, dict]:
    """Per method, the scored pixel regions and image scores of Table P; the region maps.

    Pixel regions: every region of a frame cut by its boxes and change boxes, its area, label and
    the LoC of the box that owns it (the frame's lowest LoC where no box covers it). Images: the
    frame's largest LoC. The maps, per box set ("fused" or "orig"), give the regions' owners
    and the boxes by image, for the floor (random box scores) and ceiling (box RoC).
    """
    cb = change_boxes(ann)
    size = frame_sizes(frames)
    low = {
        m: float(np.nanmin(samples[f"loc_{m}"].to_numpy()))
        if samples[f"loc_{m}"].notna().any()
        else 0.0
        for m in methods
    }
    px: dict[str, dict[str, list]] = {m: {"s": [], "y": [], "w": [], "g": []} for m in methods}
    img: dict[str, dict[str, list]] = {m: {"s": [], "y": [], "g": []} for m in methods}
    groups = sample_groups(samples)
    boxes = samples[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    locs = {m: samples[f"loc_{m}"].to_numpy(np.float64) for m in methods}
    fused_methods = [m for m in methods if not is_unfused(m)]
    in_fused = (
        np.isfinite(np.column_stack([locs[m] for m in fused_methods])).any(1)
        if fused_methods
        else np.zeros(len(samples), bool)
    )
    qs, qc, qu = (
        samples["q_session"].to_numpy(),
        samples["q_camera"].to_numpy(),
        samples["q_utime"].to_numpy(),
    )
    # per box set ("fused" or "orig"): its regions (owner = sample row, -1 uncovered) and its boxes
    # by image, for the floor (random box scores) and ceiling (box RoC) through the same maps
    maps: dict[str, dict[str, list]] = {
        k: {"row": [], "y": [], "w": [], "units": [], "img_y": []} for k in ("fused", "orig")
    }
    for gkey, idx in pd.Series(np.arange(len(samples))).groupby(groups, sort=True).indices.items():
        qk = (str(qs[idx[0]]), str(qc[idx[0]]), int(qu[idx[0]]))
        w, h = map(float, size[qk])
        change = cb.get(qk, np.zeros((0, 4)))
        gid = ids[gkey]
        sets = _box_sets(idx, in_fused, locs, methods)
        regions = {}
        for k, v in sets.items():
            regions[k] = _merged_regions(boxes[v], change, w, h)
            a, y, own = regions[k]
            maps[k]["row"].append(np.where(own >= 0, v[np.maximum(own, 0)] if len(v) else -1, -1))
            maps[k]["y"].append(y)
            maps[k]["w"].append(a)
            if len(v):
                maps[k]["units"].append(v)
                maps[k]["img_y"].append(bool(len(change)))
        for m in methods:
            key = "orig" if is_unfused(m) else "fused"
            area, pos, owner = regions[key]
            vals = locs[m][sets[key]]
            px[m]["s"].append(region_scores(vals, owner, low[m])[0])
            px[m]["y"].append(pos)
            px[m]["w"].append(area)
            px[m]["g"].append(np.full(len(area), gid))
            v = locs[m][idx]
            if np.isfinite(v).any():
                img[m]["s"].append(float(np.nanmax(v)))
                img[m]["y"].append(bool(len(change)))
                img[m]["g"].append(gid)
    return px, img, maps


def _p_ap(name: str, d: dict[str, list]) -> tuple[float, np.ndarray, dict, Any]:
    """AP of one method's pixel regions (area-weighted) or images, with its groups and counts.

    Also the bootstrap of the same AP (a partial of :func:`bootstrap_aps`).
    """
    if name == "pixel":
        s_ = np.concatenate(d["s"]) if d["s"] else np.zeros(0)
        y_ = np.concatenate(d["y"]).astype(bool) if d["y"] else np.zeros(0, bool)
        w_ = np.concatenate(d["w"]) if d["w"] else np.zeros(0)
        g_ = np.concatenate(d["g"]) if d["g"] else np.zeros(0, np.int64)
        ap = weighted_average_precision(y_, s_, w_)
        pos_w, tot_w = float(w_[y_].sum()), float(w_.sum())

        boot = partial(bootstrap_aps, y_, s_, g_, weights=w_)

        extra = {
            "positives": round(pos_w),
            "negatives": round(tot_w - pos_w),
            "positive_rate": pos_w / tot_w if tot_w else float("nan"),
            "_positive_groups": y_ & (w_ > 0),
        }
    else:
        s_, y_, g_ = (
            np.asarray(d["s"], np.float64),
            np.asarray(d["y"], bool),
            np.asarray(d["g"], np.int64),
        )
        ap = average_precision(y_, s_)

        boot = partial(bootstrap_aps, y_, s_, g_)

        extra = {
            "positives": int(y_.sum()),
            "negatives": int((~y_).sum()),
            "positive_rate": float(y_.mean()) if len(y_) else float("nan"),
            "_positive_groups": y_,
        }
    return ap, g_, extra, boot


def _map_chance(
    cfg: EvalSettings, maps: dict[str, dict[str, list]], roc: np.ndarray
) -> dict[tuple[str, str], tuple[tuple[float, float, float], float]]:
    """Table P's floor, chance band and ceiling per (pixel or image, box set), method §9.

    Floor: every box of the set takes a uniform random score, pixels take the score of the box
    that owns them in the method's map (uncovered pixels the lowest score of the draw) and each
    image the largest score of its boxes, as the real figures do. Ceiling: every box scored by its
    RoC through the same maps (the best any LoC could do with these boxes).
    """
    out = {}
    nan3 = (float("nan"),) * 3
    for key, mp in maps.items():
        if not mp["units"]:
            out[("pixel", key)] = out[("image", key)] = (nan3, float("nan"))
            continue
        units = np.concatenate(mp["units"])
        unit_of = np.full(len(roc), -1, np.int64)
        unit_of[units] = np.arange(len(units))
        row = np.concatenate(mp["row"])
        ru = np.where(row >= 0, unit_of[np.maximum(row, 0)], -1)
        y, w = np.concatenate(mp["y"]).astype(bool), np.concatenate(mp["w"])
        starts = np.cumsum([0] + [len(u) for u in mp["units"][:-1]])
        img_y = np.asarray(mp["img_y"], bool)

        def pixel(
            s: np.ndarray, y: np.ndarray = y, w: np.ndarray = w, ru: np.ndarray = ru
        ) -> np.ndarray:
            return chance.aps_of_rows(y, region_scores(s, ru), w)

        def image(s: np.ndarray, starts: np.ndarray = starts, img_y: np.ndarray = img_y):
            return chance.aps_of_rows(img_y, np.maximum.reduceat(s, starts, axis=1))

        draws, n = cfg.report.chance_draws, len(units)
        oracle = roc[units][None, :]
        for name, fig in (("pixel", pixel), ("image", image)):
            seed = chance.draw_seed(cfg.seed, "P", name, key, n)
            out[(name, key)] = (
                chance.summarise(chance.random_draws(fig, n, draws, seed)),
                float(fig(oracle)[0]),
            )
    return out

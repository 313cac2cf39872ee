"""Frames that carry no place (docs/decisions.md, *Frames that carry no place*).

A camera starting up in the dark, a tunnel, a lens cap, an overexposed or blank frame: too little
contrast to say where it is. Such a frame's patch-normalised thumbnail sits at a small distance
from every other frame, so a handful of them would capture every query of a sequence. They are
found before pairing by their **contrast**, the standard deviation of the frame's grey levels
(0-255, on a copy at most ``SIDE`` pixels on the longer side), and take no part in pairing: a map
frame with no place is nobody's pair, a query frame with no place gets none.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.imagestore import read_image
from harness.records import FRAME_KEY, QUERY_KEY

log = logging.getLogger(__name__)

#: The longer side of the copy the contrast is measured on (pixels).
SIDE = 256


def contrast(rgb: np.ndarray) -> float:
    """The standard deviation of a frame's grey levels (0-255) on a copy ``SIDE`` px long."""
    g = rgb if rgb.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    h, w = g.shape[:2]
    f = min(1.0, SIDE / float(max(h, w)))
    if f < 1:
        g = cv2.resize(
            g, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA
        )
    return float(np.asarray(g, np.float64).std())


def no_place(images: Iterable[tuple[tuple[str, str, int], str]], threshold: float) -> dict:
    """The frames whose contrast is below ``threshold``: frame key -> its contrast.

    ``images``: (frame key, image URI) pairs; nothing is read where ``threshold`` is 0.
    """
    if threshold <= 0:
        return {}
    out = {}
    for key, uri in images:
        c = contrast(read_image(str(uri)))
        if c < threshold:
            out[key] = c
    return out


def without_no_place(
    candidates: pd.DataFrame, frames: pd.DataFrame, threshold: float
) -> tuple[pd.DataFrame, dict, pd.MultiIndex | None]:
    """The candidates less the query frames that carry no place (:mod:`harness.pairs.place`).

    Returns them, every frame of the sessions involved that carries no place (its contrast by
    frame key) and those keys.
    """
    involved = set(candidates["q_session"]) | set(candidates["r_session"])
    fr = frames[frames["session"].isin(involved)]
    blank = no_place(
        (((str(s), str(c), int(u)), uri) for s, c, u, uri in fr[[*FRAME_KEY, "image"]].to_numpy()),
        threshold,
    )
    keys = pd.MultiIndex.from_tuples(sorted(blank), names=FRAME_KEY) if blank else None
    if keys is not None:
        q_keys = pd.MultiIndex.from_frame(candidates[QUERY_KEY].set_axis(FRAME_KEY, axis=1))
        candidates = candidates[~q_keys.isin(keys)]
    return candidates, blank, keys


def no_place_summary(blank: dict, threshold: float) -> dict[str, Any]:
    """``summary.json``'s ``no_place``: the measure, the threshold and each frame's contrast."""
    return {
        "measure": "the standard deviation of the frame's grey levels (0-255)",
        "min_place_contrast": threshold,
        "frames": [
            {"session": k[0], "camera": k[1], "utime": k[2], "contrast": round(v, 2)}
            for k, v in sorted(blank.items())
        ],
    }


def _names(names: pd.DataFrame) -> dict[tuple[str, str, int], str]:
    """Each named frame's file name (folder sessions), by frame key."""
    if not len(names):
        return {}
    return {
        (str(r.session), str(r.camera), int(r.utime)): str(r.name)
        for r in names.itertuples(index=False)
    }


def no_place_report(summary: Path, names: pd.DataFrame) -> dict[str, Any] | None:
    """The pairing's frames that carry no place (its ``summary.json``), with their file names.

    A WARNING names them. None where the summary holds no such record.
    """
    if not summary.is_file():
        return None
    got = json.loads(summary.read_text()).get("no_place")
    if not got:
        return None
    found = got["frames"]
    if found:
        by_key = _names(names)
        label = [
            by_key.get((f["session"], f["camera"], int(f["utime"])), f"{f['session']} {f['utime']}")
            for f in found
        ]
        got["names"] = label
        shown = ", ".join(label[:10]) + (f" and {len(label) - 10} more" if len(label) > 10 else "")
        log.warning(
            "%d frames carry no place (grey-level standard deviation under [pairs] "
            "min_place_contrast = %g: dark, blank or a tunnel): no map frame of theirs is a pair, "
            "no query frame of theirs gets one: %s",
            len(found), got["min_place_contrast"], shown,
        )  # fmt: skip
    return dict(got)


def unpaired_report(summary: Path, names: pd.DataFrame) -> list[dict[str, Any]]:
    """The query frames a sequence's path left unpaired (its ``summary.json``), with file names.

    A WARNING names them and says why (:mod:`harness.pairs.sequence`); none outside a sequence.
    """
    if not summary.is_file():
        return []
    got = json.loads(summary.read_text()).get("unpaired") or []
    by_key = _names(names)
    for f in got:
        f["name"] = by_key.get((f["session"], f["camera"], int(f["utime"])), str(f["utime"]))
    for why in sorted({f["why"] for f in got}):
        mine = [f["name"] for f in got if f["why"] == why]
        shown = ", ".join(mine[:10]) + (f" and {len(mine) - 10} more" if len(mine) > 10 else "")
        log.warning("%d query frames are left unpaired (%s): %s", len(mine), why, shown)
    return list(got)


def hub_report(pairs: pd.DataFrame, frames: pd.DataFrame, names: pd.DataFrame) -> list[dict]:
    """Map frames that are the pair of far more query frames than a route allows: a WARNING each.

    At the slowest speed a sequence may run (half a map frame per query frame) a map frame is
    the pair of about two consecutive query frames; one that is the pair of more than four times
    the query-to-map ratio (and more than 5 frames) is a hub, as a blank or dark frame would be.
    """
    hubs: list[dict] = []
    by_key = _names(names)
    for rs, g in pairs.groupby("r_session", sort=True) if len(pairs) else []:
        n_q = len(g)
        n_map = int((frames["session"] == rs).sum()) or 1
        limit = max(5, int(np.ceil(4 * n_q / n_map)))
        counts = g.groupby(["r_camera", "r_utime"], sort=True).size()
        for (cam, ut), n in counts[counts > limit].items():
            key = (str(rs), str(cam), int(str(ut)))
            hubs.append({"session": key[0], "camera": key[1], "utime": key[2], "pairs": int(n),
                         "of": n_q, "limit": limit, "name": by_key.get(key, str(ut))})  # fmt: skip
            log.warning(
                "map frame %s of %s is the pair of %d of %d query frames (a route allows about "
                "%d): a hub, as a blank, dark or repeated frame would be; its pairs may not "
                "show the same place",
                hubs[-1]["name"], key[0], int(n), n_q, limit,
            )  # fmt: skip
    return hubs

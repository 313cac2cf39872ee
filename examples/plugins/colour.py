"""A localizer kind that caches: each subimage's RGB histogram, ranked by the harness's engine.

A plugin: then a ``[[localizers]]`` entry may say ``colour = { bins = 4 }``. The histograms of a
session are one cache entry (``p.unit``), so a second run reuses them.
"""

from dataclasses import dataclass
from functools import partial

import cv2
import numpy as np

from harness.imagestore import read_image
from harness.localizers.kinds import LocalizerKind, register_localizer_kind
from harness.records import FRAME_KEY
from harness.runtime.cache import write_parquet


@dataclass(frozen=True)
class Colour:
    """A ``colour`` localizer's table."""

    bins: int = 4  # per RGB channel


def describe(bins, rows, frames, tmp):
    """Each subimage's square-rooted RGB histogram (``desc.npy``) and its rows, into ``tmp``."""
    uris = rows.merge(frames[[*FRAME_KEY, "image"]], on=FRAME_KEY, how="left")["image"]
    out = []
    for r, uri in zip(rows.itertuples(), uris, strict=True):
        crop = read_image(uri)[int(r.y1) : int(r.y2), int(r.x1) : int(r.x2)]
        h = cv2.calcHist([crop], [0, 1, 2], None, [bins] * 3, [0, 256] * 3).ravel()
        out.append(np.sqrt(h / max(h.sum(), 1.0)))
    np.save(tmp / "desc.npy", np.asarray(out, np.float32).reshape(len(rows), bins**3))
    write_parquet(tmp / "index.parquet", rows)
    return {}


def colour_ranks(p, loc, frames, pairs, props, rc):
    """The kind's ranks: every session's histograms (cached), ranked by the exact engine."""
    bins = loc.options.bins
    described = {
        s: p.unit("colour", (bins, t.key), partial(describe, bins, t.df, frames.df))
        for s, t in props.items()
    }
    return p.query_ranks(frames, pairs, described, rc)


register_localizer_kind(LocalizerKind("colour", Colour, ranks=colour_ranks))

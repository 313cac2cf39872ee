"""What a localizer costs (Table L's cost columns): storage a robot keeps, time to encode and rank.

Measured in the run from the cache entries the localizer used: their files (the descriptors a map
holds) and the seconds their builds took where they were built (``build_s`` in each entry's
manifest; a cached entry keeps the time of the run that built it). Times include everything the
stage does (decoding the frame and cutting the crops count as encoding), on the machine named by
:func:`machine`.
"""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

#: The stages of each cost (the localizer kinds use one of each group).
BUILD_STAGES = ("model", "projection", "bovw_vocab")
ENCODE_STAGES = ("descriptor_shards", "bovw_shards")
STORE_STAGES = ("descriptors", "bovw_words")
RANK_STAGES = ("ranks",)

#: Table L's cost columns: (column, heading, decimals).
COST_COLUMNS = (
    ("descriptor_bytes", "bytes/subimage", 0),
    ("map_kib_per_frame", "map KiB/frame", 1),
    ("encode_ms", "encode ms/subimage", 2),
    ("rank_ms", "rank ms/query subimage", 3),
    ("build_s", "build s", 1),
)
#: Why an imported localizer has no cost cells.
IMPORTED_WHY = "an imported ranked list: the harness never holds its descriptors or its engine"


def _build_s(entry: Path) -> float:
    try:
        v = json.loads((entry / "manifest.json").read_text()).get("build_s")
    except (OSError, ValueError):
        return float("nan")
    return float(v) if isinstance(v, (int, float)) else float("nan")


def _stored(entry: Path) -> tuple[int, int]:
    """(bytes, rows) of the descriptors an entry holds (dense ``desc.npy`` or sparse words)."""
    npy = entry / "desc.npy"
    if npy.is_file():
        a = np.load(npy, mmap_mode="r")
        return int(a.nbytes), int(a.shape[0])
    npz = entry / "words.npz"
    if npz.is_file():
        import scipy.sparse as sp

        m = sp.load_npz(npz).tocsr()
        return int(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes), int(m.shape[0])
    return 0, 0


def localizer_costs(
    trail: Iterable[tuple[str, Path]],
    query_subimages: int,
    ref_subimages: int,
    ref_frames: int,
    imported: bool = False,
) -> dict[str, float]:
    """Table L's cost cells of one localizer from the entries it used (``trail``).

    Args:
        trail: (stage, entry directory) of every entry the localizer's stages used.
        query_subimages: its ranked query subimages (the rank time's denominator).
        ref_subimages: subimages of the reference sessions (the map's descriptors).
        ref_frames: frames of the reference sessions holding them.
        imported: an imported list (no cost is known: every cell NaN).

    Returns:
        Each of :data:`COST_COLUMNS` (NaN where not measured) and ``imported`` (1.0 or 0.0).
    """
    nan = float("nan")
    out = dict.fromkeys((c for c, *_ in COST_COLUMNS), nan)
    out["imported"] = float(imported)
    if imported:
        return out
    seen: dict[Path, str] = {}
    for stage, path in trail:
        seen.setdefault(Path(path), stage)
    by: dict[str, list[Path]] = {}
    for path, stage in seen.items():
        by.setdefault(stage, []).append(path)

    def total(stages: tuple[str, ...]) -> float:
        return float(sum(_build_s(e) for s in stages for e in by.get(s, [])))

    nbytes = rows = 0
    for s in STORE_STAGES:
        for e in by.get(s, []):
            b, r = _stored(e)
            nbytes, rows = nbytes + b, rows + r
    if rows:
        per = nbytes / rows
        out["descriptor_bytes"] = round(per, 1)
        if ref_frames:
            out["map_kib_per_frame"] = per * ref_subimages / ref_frames / 1024.0
    encoded = rows  # every stored row was encoded once
    if encoded and any(by.get(s) for s in ENCODE_STAGES):
        out["encode_ms"] = 1000.0 * total(ENCODE_STAGES) / encoded
    if query_subimages and by.get("ranks"):
        out["rank_ms"] = 1000.0 * total(RANK_STAGES) / query_subimages
    if any(by.get(s) for s in BUILD_STAGES):
        out["build_s"] = total(BUILD_STAGES)
    return out


def machine() -> str:
    """The CPU (and GPU, where torch sees one) the costs were measured on, in words."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    gpu = "no GPU"
    try:
        import torch

        if torch.cuda.is_available():
            gpu = f"GPU {torch.cuda.get_device_name(0)}"
    except Exception:
        pass
    return f"{cpu}, {n} cores, {gpu}"


def cost_record(costs: dict[str, Any]) -> dict[str, Any]:
    """The cost cells as ``run.json`` keeps them (rounded; NaN as None)."""
    return {k: (None if v != v else round(float(v), 4)) for k, v in costs.items()}

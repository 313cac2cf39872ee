"""The run record (``run.json``): what ran, on what, with which versions and cache entries."""

from __future__ import annotations

import json
import platform
import sys
from dataclasses import asdict, dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness import __version__, kernels
from harness.config.plugins import plugin_record
from harness.pipeline.context import Context, localizer_record
from harness.pipeline.localizer_stages import (
    Measured,
)
from harness.records import FRAME_KEY
from harness.reports.blocks import Reports
from harness.runtime.costs import cost_record, machine
from harness.runtime.stage import Entry, Table

#: What :func:`harness.pipeline.chain.until_ranks` gives: the ingested sessions, the frames, the
#: annotations, the pairs and each localizer's measured ranks.
Ranked = tuple[dict[str, Entry], Table, Table, Table, list[Measured]]


@dataclass(frozen=True)
class RunOutcome:
    """What a run wrote after its ranks: each block's keys, the samples, the reports, its time."""

    block_keys: dict[str, dict[str, str]]
    n_samples: int
    reports: Reports
    seconds: float


def run_record(p: Context, ranked: Ranked, outcome: RunOutcome) -> dict[str, Any]:
    """What ``run.json`` records.

    Config, versions, timings, counts, keys, warnings, cache entries. With several localizers the
    rank counters and keys are given per localizer (``keys.localizers``).
    """
    ingested, frames, ann, pairs, measured = ranked
    block_keys, n_samples = outcome.block_keys, outcome.n_samples
    reports, seconds = outcome.reports, outcome.seconds
    multi = len(measured) > 1
    first = measured[0]
    rank_counts: Any = (
        {m.loc.name: m.ranks.counts for m in measured} if multi else first.ranks.counts
    )
    unranked = sum(
        int(c.get("unranked_query_images", 0))
        for m in measured
        for c in m.ranks.counts.values()
        if isinstance(c, dict)
    )
    return {
        "config": asdict(p.cfg),
        "versions": _versions(),
        **({"plugins": plugin_record()} if plugin_record() else {}),
        "kernels": kernels.report(),
        "seed": p.cfg.seed,
        "argv": sys.argv,
        "localizers": [localizer_record(m.loc, multi) for m in measured],
        "timings_s": {k: round(v, 3) for k, v in p.timings.items()},
        "total_s": round(seconds, 3),
        "stage_units_run": p.ran,
        "executor": p.executor.describe(),
        "counts": {
            "frames": len(frames.df),
            "annotated_frames": int(ann.df[FRAME_KEY].drop_duplicates().shape[0]),
            "pairs": len(pairs.df),
            "frames_not_described": dict(sorted(p.not_described.items())),
            "ranked_subimages": sum(len(m.ranks.df) for m in measured),
            "unranked_query_images": unranked,
            "samples": n_samples,
            "rank_counts": rank_counts,
        },
        **({"pairing": p.pairing} if p.pairing else {}),
        "keys": {
            "frames": frames.key,
            "pairs": pairs.key,
            **block_keys[first.loc.name],
            **({"localizers": block_keys} if multi else {}),
        },
        "localization": reports.localization.to_dict(orient="records"),
        # Table L's cost columns, and the machine they were measured on
        "costs": {
            "machine": machine(),
            "localizers": {m.loc.name: cost_record(m.costs) for m in measured},
        },
        "warnings": reports.warnings,
        "ingest": {
            name: ingest_summary(e.path / "ingest_report.json") for name, e in ingested.items()
        },
        "cache_entries": {stage: sorted(keys_) for stage, keys_ in sorted(p.used.items())},
    }


def ingest_summary(path: Path) -> dict[str, Any]:
    """What run.json keeps of a session's ingest report: frames written, drops, pose frames."""
    rep = json.loads(path.read_text())
    return {
        k: rep[k]
        for k in ("format", "frames_written", "dropped", "pose_frames", "salvaged")
        if k in rep
    }


def _torch_source() -> str:
    """Where torch came from: the file ``make setup``'s torch step recorded, else "?".

    The step (tools/install_torch.py) writes ``torch-source.json`` into the environment it
    installs into; an environment set up by hand has none.
    """
    try:
        return str(json.loads((Path(sys.prefix) / "torch-source.json").read_text())["from"])
    except (OSError, ValueError, KeyError, TypeError):
        return "?"


def _versions() -> dict[str, str]:
    import torch  # heavy: only where a run records its versions

    def ver(dist: str) -> str:
        try:
            return version(dist)
        except PackageNotFoundError:
            return "?"

    return {
        "dbl-harness": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "pandas": pd.__version__,
        "torch": torch.__version__,
        "torch_from": _torch_source(),
        "opencv": cv2.__version__,
        "rosbags": ver("rosbags"),
        "mcap": ver("mcap"),
        "platform": platform.platform(),
    }

"""The whole NCLT's trajectory lengths, read from its ground truth where the logs are at hand.

The full-NCLT projection proposes and encodes one reference frame per ``db_stride_m`` metres of each
session's trajectory, so its workload rests on the four sessions' lengths. With the logs laid out
as ``datasets/nclt.toml`` reads them (``<root>/ground_truth/groundtruth_<date>.csv``) and
``$BENCH_NCLT_ROOT`` pointing there, the lengths are measured from the ground truth (the x-y path,
summed between consecutive poses); without them the case states its assumption instead.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

import numpy as np

from .common import ROOT

#: Where the bench looks for the NCLT logs (the directory ``make reproduce-table DATA=...`` reads).
ENV = "BENCH_NCLT_ROOT"


def session_names(config: Path = ROOT / "datasets" / "nclt.toml") -> list[str]:
    """The paper's four sessions, as the NCLT config names them."""
    return [s["name"] for s in tomllib.loads(config.read_text())["sessions"]]


def path_length_m(xy: np.ndarray) -> float:
    """The length of the x-y path through ``xy`` (n, 2) in metres: the sum of its steps."""
    return float(np.hypot(*np.diff(xy, axis=0).T).sum()) if len(xy) > 1 else 0.0


def session_lengths(root: str | None = None) -> dict[str, float] | None:
    """Each session's trajectory length in metres from ``root``'s ground truth.

    ``root`` defaults to ``$BENCH_NCLT_ROOT``; None where it is unset or a session's ground truth
    is missing (the projection then says what it assumed).
    """
    from harness.ingest import read_nclt_groundtruth

    root = root if root is not None else os.environ.get(ENV)
    if not root:
        return None
    out = {}
    for name in session_names():
        path = Path(root) / "ground_truth" / f"groundtruth_{name}.csv"
        if not path.is_file():
            return None
        _, values, _, _ = read_nclt_groundtruth(path)
        out[name] = path_length_m(values[:, :2])
    return out

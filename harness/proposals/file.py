"""Proposer ``file``: boxes from a table the user provides (any other detector)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from harness.errors import AnnotationError, ConfigError
from harness.methods import proposer
from harness.proposals.config import ProposalsConfig
from harness.records import FRAME_KEY


def load_file_proposals(path: Path, frames: pd.DataFrame) -> pd.DataFrame:
    """A user's proposal table (CSV or parquet).

    Columns ``session, camera, utime, x1, y1, x2, y2`` [, ``score``, ``class``].

    Raises:
        AnnotationError: naming the row: unknown frame, box of zero area or outside the image.
    """
    path = Path(path)
    if not path.exists():
        raise AnnotationError(f"{path}: proposal file not found")
    df = (
        pd.read_parquet(path)
        if path.suffix == ".parquet"
        else pd.read_csv(path, dtype={"session": str, "camera": str})
    )
    need = ["session", "camera", "utime", "x1", "y1", "x2", "y2"]
    miss = [c for c in need if c not in df.columns]
    if miss:
        raise AnnotationError(f"{path}: missing column(s) {miss}; expected {need} [+ score, class]")
    df = df.reset_index(drop=True)
    df["score"] = df["score"].astype(float) if "score" in df.columns else 1.0
    df["class"] = df["class"].astype(str) if "class" in df.columns else ""
    keys = FRAME_KEY
    m = df.merge(frames[keys + ["width", "height"]].drop_duplicates(keys), on=keys, how="left")
    b = df[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    checks = [
        (m["width"].isna().to_numpy(), "unknown frame"),
        (~np.isfinite(b).all(1), "non-numeric box"),
        ((b[:, 2] <= b[:, 0]) | (b[:, 3] <= b[:, 1]), "box has zero or negative area"),
        (
            (b[:, 0] < 0)
            | (b[:, 1] < 0)
            | (b[:, 2] > m["width"].to_numpy())
            | (b[:, 3] > m["height"].to_numpy()),
            "box outside the image",
        ),
    ]
    for mask, what in checks:
        mask = np.asarray(mask, bool)
        if mask.any():
            i = int(np.nonzero(mask)[0][0])
            raise AnnotationError(f"{path}: row {i + 1}: {what} ({int(mask.sum())} row(s) in all)")
    return df


@proposer("file")
def file_proposals(frames: pd.DataFrame, cfg: ProposalsConfig) -> pd.DataFrame:
    """The rows of method ``file``: the user's table, numbered per frame in box order."""
    if not cfg.file:
        raise ConfigError("[proposals] method 'file' needs [proposals] file = <path to the table>")
    fp = load_file_proposals(Path(cfg.file), frames)
    fp = fp.merge(frames[FRAME_KEY], on=FRAME_KEY)
    fp = fp.sort_values(["session", "camera", "utime", "x1", "y1", "x2", "y2"]).reset_index(
        drop=True
    )
    fp["proposal_method"] = "file"
    fp["box_id"] = fp.groupby(FRAME_KEY).cumcount().astype(np.int32)
    return fp

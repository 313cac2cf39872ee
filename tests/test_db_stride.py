"""``[retrieval] db_stride_m``: the reference database by place (issue 15's first step)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from harness.runner import Pipeline


def _variant(local_run: tuple, tmp_path: Path, name: str, **retrieval: float) -> tuple[dict, Path]:
    p, _, out = local_run
    shutil.copytree(out / "cache", tmp_path / name / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / name / ".dbl-harness.json")
    cfg = dataclasses.replace(p.cfg, retrieval=dataclasses.replace(p.cfg.retrieval, **retrieval))
    q = Pipeline(cfg, tmp_path / name)
    rec = q.run()
    assert q.ran.get("descriptors", 0) == 0 and q.ran.get("model", 0) == 0  # only ranks and what follows
    return rec, tmp_path / name


def test_a_stride_below_the_frame_spacing_keeps_every_frame(local_run: tuple, tmp_path: Path) -> None:
    _, _, out = local_run
    _, o = _variant(local_run, tmp_path, "fine", db_stride_m=0.01)  # fixture frames are metres apart
    assert (o / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
    pd.testing.assert_frame_equal(pd.read_parquet(o / "ranks.parquet"), pd.read_parquet(out / "ranks.parquet"))


def test_a_thinned_database_ranks_against_fewer_frames_and_counts_lost_places(local_run: tuple, tmp_path: Path) -> None:
    _, _, out = local_run
    full = pd.read_parquet(out / "ranks.parquet")
    rec, o = _variant(local_run, tmp_path, "thin", db_stride_m=9.0, gt_radius_m=5.0)
    thin = pd.read_parquet(o / "ranks.parquet")
    assert thin["L"].max() < full["L"].max() * 0.75  # about every other frame of the loop is kept
    counts = rec["counts"]["rank_counts"]
    lost = sum(c.get("no_rank_place_not_in_database", 0) for c in counts.values())
    assert lost >= 0 and sum(c["ranked"] for c in counts.values()) == len(thin)
    assert (thin["place_size"] >= 1).all() and np.isfinite(thin["d"]).all()
    assert pd.read_csv(o / "table1.csv")["method"].tolist() == pd.read_csv(out / "table1.csv")["method"].tolist()

"""``[retrieval] db_stride_m``: the reference database by place (issue 15's first step)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.pairs.pose import thin_by_stride
from harness.pipeline.chain import Pipeline, load_run
from harness.retrieval import described_frames

from ..conftest import no_figures


def _variant(
    local_run: tuple, tmp_path: Path, name: str, reuse: bool = True, **retrieval: float
) -> tuple[dict, Path]:
    p, _, out = local_run
    shutil.copytree(out / "cache", tmp_path / name / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / name / ".dbl-harness.json")
    cfg = dataclasses.replace(p.cfg, retrieval=dataclasses.replace(p.cfg.retrieval, **retrieval))
    q = Pipeline(no_figures(cfg), tmp_path / name)
    rec = q.run()
    if reuse:  # the same described frames: only ranks and what follows run again
        assert (
            q.ran.get("proposals", 0) == 0
            and q.ran.get("descriptors", 0) == 0
            and q.ran.get("model", 0) == 0
        )
    return rec, tmp_path / name


@pytest.fixture(scope="module")
def thin(local_run: tuple, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    """The fixture run with a database of one frame per 9 m (and a 5 m place), run once."""
    base = tmp_path_factory.mktemp("stride")
    return _variant(local_run, base, "thin", reuse=False, db_stride_m=9.0, gt_radius_m=5.0)


def test_a_stride_below_the_frame_spacing_keeps_every_frame(
    local_run: tuple, tmp_path: Path
) -> None:
    _, _, out = local_run
    _, o = _variant(
        local_run, tmp_path, "fine", db_stride_m=0.01
    )  # fixture frames are metres apart
    assert (o / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
    pd.testing.assert_frame_equal(
        pd.read_parquet(o / "ranks.parquet"), pd.read_parquet(out / "ranks.parquet")
    )


def test_a_thinned_database_ranks_against_fewer_frames_and_counts_lost_places(
    local_run: tuple, thin: tuple[dict, Path]
) -> None:
    _, _, out = local_run
    full = pd.read_parquet(out / "ranks.parquet")
    rec, o = thin
    thin = pd.read_parquet(o / "ranks.parquet")
    assert thin["L"].max() < full["L"].max() * 0.75  # about every other frame of the loop is kept
    counts = rec["counts"]["rank_counts"]
    lost = sum(c.get("no_rank_place_not_in_database", 0) for c in counts.values())
    ranked = sum(c["ranked"] for c in counts.values())
    assert ranked == len(thin)
    # every query subimage of the full run is asked for; those not ranked lost their place
    assert sum(c["query_subimages"] for c in counts.values()) == len(full)
    assert lost == len(full) - len(thin) > 0
    assert (thin["place_size"] >= 1).all() and np.isfinite(thin["d"]).all()
    assert (
        pd.read_csv(o / "table1.csv")["fusion"].tolist()
        == pd.read_csv(out / "table1.csv")["fusion"].tolist()
    )


def test_a_thinned_database_proposes_and_describes_only_the_frames_ranking_reads(
    thin: tuple[dict, Path],
) -> None:
    rec, o = thin
    run = load_run(o)
    frames = pd.read_parquet(o / "cache" / "frames" / run["keys"]["frames"] / "frames.parquet")
    pairs = pd.read_parquet(o / "cache" / "pairs" / run["keys"]["pairs"] / "pairs.parquet")
    not_described = rec["counts"]["frames_not_described"]
    props = {
        str(t["session"].iat[0]): t for t in _entries(o, run, "proposals", "proposals.parquet")
    }
    described = {
        str(t["session"].iat[0]): t for t in _entries(o, run, "descriptors", "index.parquet")
    }
    assert sorted(props) == sorted(described) == sorted(frames["session"].unique())
    for name, fr in frames.groupby("session"):
        fr = fr.sort_values("utime")
        kept = set(fr["utime"].to_numpy()[thin_by_stride(fr[["x", "y"]].to_numpy(), 9.0)].tolist())
        queried = set(pairs.loc[pairs["q_session"] == name, "q_utime"].tolist())
        assert set(props[name]["utime"]) == set(described[name]["utime"]) == kept | queried
        assert len(described[name]) == len(props[name])
        assert not_described[name] == len(fr) - len(kept | queried) > 0


def _entries(o: Path, run: dict, stage: str, file: str) -> list[pd.DataFrame]:
    return [pd.read_parquet(o / "cache" / stage / k / file) for k in run["cache_entries"][stage]]


def test_described_frames_by_hand() -> None:
    frames = pd.DataFrame(
        {
            "session": ["a"] * 4 + ["b"] * 3 + ["c"] * 2,
            "camera": ["Cam5"] * 9,
            "utime": [1, 2, 3, 4, 1, 2, 3, 7, 8],
            "x": [0.0, 1.0, 2.0, 3.0, 0.0, 5.0, 10.0, 0.0, 1.0],
            "y": [0.0] * 9,
        }
    )
    pairs = pd.DataFrame(
        {
            "q_session": ["a", "b"],
            "q_camera": ["Cam5", "Cam5"],
            "q_utime": [2, 2],
            "r_session": ["b", "a"],
            "r_camera": ["Cam5", "Cam5"],
            "r_utime": [1, 3],
        }
    )
    every = described_frames(frames, pairs, 0.0)
    assert every["a"]["utime"].tolist() == [1, 2, 3, 4] and every["b"]["utime"].tolist() == [
        1,
        2,
        3,
    ]
    assert every["c"].empty  # neither queried nor a reference: never proposed
    thin = described_frames(frames, pairs, 2.0)
    assert thin["a"]["utime"].tolist() == [
        1,
        2,
        3,
    ]  # kept 1 (start) and 3 (2 m travelled); 2 is a query frame
    assert thin["b"]["utime"].tolist() == [1, 2, 3]  # 5 m apart: every frame kept


def test_gt_radius_also_repeats_the_localization_table_at_the_second_radius(
    local_run: tuple, tmp_path: Path
) -> None:
    """``[report] gt_radius_also = 5`` (issue 38): ``localization_also.*`` is the localization
    table of a run whose place is 5 m wide, while every other table stays the 2 m run's; a wider
    place can only raise recall@N."""
    p, _, out = local_run
    name = "also"
    shutil.copytree(out / "cache", tmp_path / name / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / name / ".dbl-harness.json")
    cfg = dataclasses.replace(p.cfg, report=dataclasses.replace(p.cfg.report, gt_radius_also=5.0))
    q = Pipeline(cfg, tmp_path / name)
    q.run()
    o = tmp_path / name
    assert q.ran.get("descriptors", 0) == 0 and q.ran.get("model", 0) == 0  # ranked again only
    assert (o / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
    assert (o / "localization.csv").read_bytes() == (out / "localization.csv").read_bytes()
    also = pd.read_csv(o / "localization_also.csv")
    assert (also["gt_radius_m"] == 5.0).all()
    assert "within 5 m" in (o / "localization_also.md").read_text()
    _, wide = _variant(local_run, tmp_path, "wide", gt_radius_m=5.0)
    want = pd.read_csv(wide / "localization.csv")
    pd.testing.assert_frame_equal(also.drop(columns="gt_radius_m"), want)
    base = pd.read_csv(out / "localization.csv")
    for n in (1, 5, 10, 20):
        assert (also[f"recall_at_{n}"] >= base[f"recall_at_{n}"] - 1e-9).all(), n
    assert (also["recall_at_1"] > base["recall_at_1"]).any()
    assert 'id="localization-also"' in (o / "report.html").read_text()

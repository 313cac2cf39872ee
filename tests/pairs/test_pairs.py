"""Cross-season pairing: hand-computed cases and the fixture's viewpoint differences."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from harness.ingest import ingest_session, load_frames
from harness.ingest.config import IngestConfig, SessionConfig
from harness.pairs.config import PairsConfig
from harness.pairs.pose import build_pairs, nearest_with_heading, thin_by_stride
from harness.pairs.table import yaw_diff_deg


def _frames(rows: list[tuple]) -> pd.DataFrame:
    return pd.DataFrame(rows, columns=["session", "camera", "utime", "x", "y", "yaw"]).assign(
        z=0.0, roll=0.0, pitch=0.0, image="", width=10, height=10
    )


def test_yaw_difference_wraps_around() -> None:
    assert (
        yaw_diff_deg(np.radians(179), np.radians(-179)) == np.float64(2.0)
        or abs(yaw_diff_deg(np.radians(179), np.radians(-179)) - 2) < 1e-9
    )
    assert abs(yaw_diff_deg(0.0, np.pi) - 180) < 1e-9


def test_heading_filter_and_wraparound() -> None:
    fr = _frames(
        [
            ("A", "c", 1, 0.0, 0.0, np.radians(178)),
            ("B", "c", 10, 0.5, 0.0, np.radians(0)),  # nearest, but facing the other way
            ("B", "c", 11, 2.0, 0.0, np.radians(-179)),  # 3 degrees away across +-180
        ]
    )
    pairs, _ = build_pairs(fr, PairsConfig(max_distance_m=None), {"A": "WI", "B": "SU"})
    ab = pairs[pairs["q_session"] == "A"].iloc[0]
    assert (
        ab["r_utime"] == 11 and abs(ab["yaw_diff_deg"] - 3) < 1e-9 and ab["season_pair"] == "WI->SU"
    )


def test_ties_go_to_the_earlier_reference() -> None:
    fr = _frames(
        [
            ("A", "c", 1, 0.0, 0.0, 0.0),
            ("B", "c", 30, -1.0, 0.0, 0.0),
            ("B", "c", 20, 1.0, 0.0, 0.0),
        ]
    )
    pairs, _ = build_pairs(fr, PairsConfig(), {})
    assert pairs[pairs["q_session"] == "A"]["r_utime"].tolist() == [20]


def test_no_reference_in_range_is_counted() -> None:
    fr = _frames([("A", "c", 1, 0.0, 0.0, 0.0), ("B", "c", 2, 50.0, 0.0, 0.0)])
    pairs, summary = build_pairs(fr, PairsConfig(max_distance_m=10.0), {"A": "WI", "B": "SU"})
    assert len(pairs) == 0
    assert summary["no_reference_per_season_pair"] == {"SU->WI": 1, "WI->SU": 1}
    assert summary["queries_without_any_reference"] == 2


def test_kdtree_answer_equals_brute_force() -> None:
    rng = np.random.default_rng(0)
    ref = rng.uniform(0, 50, (400, 2))
    ryaw = rng.uniform(-np.pi, np.pi, 400)
    q = rng.uniform(0, 50, (60, 2))
    qyaw = rng.uniform(-np.pi, np.pi, 60)
    idx, dist = nearest_with_heading(ref, ryaw, np.arange(400), q, qyaw, 45.0, 8.0)
    for i in range(60):
        ok = (yaw_diff_deg(qyaw[i], ryaw) < 45) & (np.linalg.norm(ref - q[i], axis=1) <= 8.0)
        if not ok.any():
            assert idx[i] == -1
        else:
            d = np.where(ok, np.linalg.norm(ref - q[i], axis=1), np.inf)
            assert idx[i] == int(np.argmin(d)) and abs(dist[i] - d.min()) < 1e-12


def test_stride_thinning() -> None:
    xy = np.column_stack([np.arange(10) * 0.4, np.zeros(10)])
    assert thin_by_stride(xy, 1.0).tolist() == [0, 3, 6, 9]
    assert thin_by_stride(xy, 0).tolist() == list(range(10))


def test_fixture_every_annotated_query_gets_a_close_reference(
    default_world: Path, tmp_path: Path
) -> None:
    from harness.fixture import FixtureSpec
    from harness.fixture.generate import DEFAULT_FORMATS, session_path

    spec = FixtureSpec()
    frames = []
    for (session, _), fmt in zip(spec.sessions, DEFAULT_FORMATS, strict=True):
        ingest_session(
            SessionConfig(name=session, source=str(default_world / session_path(fmt, session))),
            IngestConfig(),
            tmp_path / session,
        )
        frames.append(load_frames(tmp_path / session / "frames.parquet"))
    fr = pd.concat(frames, ignore_index=True)
    ann = pd.read_csv(default_world / "annotations.csv")
    pairs, summary = build_pairs(fr, PairsConfig(), dict(spec.sessions), ann)
    n_q = ann[["session", "camera", "utime"]].drop_duplicates().shape[0]
    assert len(pairs) == 3 * n_q  # one reference in each other session
    assert len(summary["pairs_per_season_pair"]) == 12
    truth = pd.read_parquet(default_world / "truth" / "frames.parquet").set_index(
        ["session", "utime"]
    )
    q = truth.loc[list(zip(pairs["q_session"], pairs["q_utime"], strict=True))]
    r = truth.loc[list(zip(pairs["r_session"], pairs["r_utime"], strict=True))]
    dist = np.hypot(q["x"].to_numpy() - r["x"].to_numpy(), q["y"].to_numpy() - r["y"].to_numpy())
    assert dist.max() < 4.0 and np.median(dist) < 2.0
    assert yaw_diff_deg(q["yaw"].to_numpy(), r["yaw"].to_numpy()).max() < 20

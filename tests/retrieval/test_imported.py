"""``harness.retrieval.imported``: a user's ranked lists, scored and checked as method §12 says.

Unit cases on a hand-made session B (frames 10..50 on a line) where every rank, ``L`` and ``d``
was worked out by hand; the CLI cases (a whole run, the report page) are in
``test_byo_localizer.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.errors import RetrievalError
from harness.retrieval.import_file import parse_import_arg, read_import
from harness.retrieval.imported import ranks_from_import

PAIRS = pd.DataFrame(
    {
        "q_session": ["A"],
        "q_camera": ["c"],
        "q_utime": [1],
        "r_session": ["B"],
        "r_camera": ["c"],
        "r_utime": [30],
        "season_pair": ["WI->SU"],
    }
)
# G = 30 at x = 10; frame 40 at x = 11 lies in its place (radius 2 m), the others do not
FRAMES = pd.DataFrame(
    {
        "session": ["A"] + ["B"] * 5,
        "camera": "c",
        "utime": [1, 10, 20, 30, 40, 50],
        "x": [10.0, 0.0, 5.0, 10.0, 11.0, 20.0],
        "y": 0.0,
        "yaw": 0.0,
    }
)
PROPOSALS = pd.DataFrame(
    {
        "session": ["A"] + ["B"] * 5,
        "camera": "c",
        "utime": [1, 10, 20, 30, 40, 50],
        "proposal_method": "grid5",
        "box_id": 0,
        "x1": 0.0,
        "y1": 0.0,
        "x2": 5.0,
        "y2": 5.0,
    }
)


def _csv(tmp: Path, rows: list[dict], name: str = "r.csv") -> Path:
    base = {
        "q_session": "A",
        "q_camera": "c",
        "q_utime": 1,
        "proposal_method": "grid5",
        "box_id": 0,
        "x1": 0.0,
        "y1": 0.0,
        "x2": 5.0,
        "y2": 5.0,
        "r_session": "B",
        "L": 5,
    }
    pd.DataFrame([{**base, **r} for r in rows]).to_csv(tmp / name, index=False)
    return tmp / name


def _rank(path: Path, radius: float = 2.0, kind: str = "distance") -> pd.DataFrame:
    df, rows = read_import(path)
    out, _ = ranks_from_import(df, rows, PAIRS, FRAMES, PROPOSALS, radius, 45.0, kind)
    return out


def test_a_strict_order_without_scores(tmp_path: Path) -> None:
    out = _rank(_csv(tmp_path, [{"ranked": "10 40 30 20 50"}]))
    # 10 lies before 40 (the place's first frame): rank 2; L = 1 + 3 frames outside the place
    assert out.loc[0, ["rank", "L", "place_size"]].tolist() == [2, 4, 2]
    assert out["r"][0] == pytest.approx(0.5) and out["r_desc"][0] == pytest.approx(0.75)
    assert np.isnan(out["d"][0]) and out["exact"][0]
    single = _rank(_csv(tmp_path, [{"ranked": "10 40 30 20 50"}]), radius=0.0)
    assert single.loc[0, ["rank", "L"]].tolist() == [3, 5]  # G alone: 10 and 40 before it


def test_scores_give_ties_in_the_querys_favour_and_d(tmp_path: Path) -> None:
    # 10 and 40 share the best distance: 10 does not count (a tie), d = 0.2 (from 40)
    out = _rank(_csv(tmp_path, [{"ranked": "10 40 30 20 50", "scores": "0.2 0.2 0.3 0.5 0.9"}]))
    assert out.loc[0, ["rank", "L"]].tolist() == [1, 4] and out["d"][0] == pytest.approx(0.2)
    out = _rank(_csv(tmp_path, [{"ranked": "10 20 40 30 50", "scores": "0.1 0.15 0.2 0.3 0.9"}]))
    assert out["rank"][0] == 3 and out["d"][0] == pytest.approx(0.2)
    sim = _rank(
        _csv(tmp_path, [{"ranked": "10 20 40 30 50", "scores": "0.9 0.85 0.8 0.7 0.1"}]),
        kind="similarity",
    )
    assert sim["rank"][0] == 3 and sim["d"][0] == pytest.approx(1 - 0.8)  # d = 1 - s


def test_the_old_column_name_method_is_read_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    new = _rank(_csv(tmp_path, [{"ranked": "10 40 30 20 50"}]))
    old = _csv(tmp_path, [{"ranked": "10 40 30 20 50"}], "old.csv")
    pd.read_csv(old).rename(columns={"proposal_method": "method"}).to_csv(old, index=False)
    with caplog.at_level("WARNING"):
        got = _rank(old)
    pd.testing.assert_frame_equal(got, new)
    assert "column 'method' read as 'proposal_method'" in caplog.text and "old.csv" in caplog.text
    both = pd.read_csv(old).assign(proposal_method="grid5")
    both.to_csv(old, index=False)
    with pytest.raises(
        RetrievalError, match=r"old.csv: columns 'method' and 'proposal_method' both"
    ):
        _rank(old)


def test_a_truncated_list_without_the_place_is_a_bound(tmp_path: Path) -> None:
    out = _rank(_csv(tmp_path, [{"ranked": "10 20", "scores": "0.1 0.4"}]))
    assert out["rank"][0] == 3 and not out["exact"][0] and out["d"][0] == pytest.approx(0.4)
    with pytest.raises(RetrievalError, match=r"complete list .* without any frame of the place"):
        _rank(_csv(tmp_path, [{"ranked": "10 20", "L": 2}]))


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ({"ranked": "10 40", "q_utime": 1000}, r"match no pair .*looks like nanoseconds"),
        ({"ranked": "10 40", "q_camera": "C"}, r"match no pair .*no camera 'C'.*case-sensitive"),
        ({"ranked": "10 40", "r_session": "A"}, r"match no pair .*reference sessions"),
        ({"ranked": "10000 40000"}, r"not frames of their reference session .*nanoseconds"),
        ({"ranked": "10 40", "scores": "0.1 nan"}, "non-finite scores"),
        ({"ranked": "10 40", "scores": "0.1"}, "another length"),
        ({"ranked": "10 40", "scores": "0.9 0.1"}, 'score_kind = "similarity"'),
        ({"ranked": "10 40 20 30 50 60", "L": 5}, "L shorter than"),
        ({"ranked": ""}, "empty 'ranked'"),
        ({"ranked": "10,40"}, r"not a list of integer .*'10,40'"),
        ({"ranked": "10 40", "box_id": "one"}, "box_id that is not an integer"),
        ({"ranked": "10 40", "x2": -1.0}, "reversed or empty"),
        ({"ranked": "10 40", "y1": "nan"}, "y1 that is not a finite number"),
        ({"ranked": "10 40", "box_id": 3}, r"match no proposal .*box 3"),
        ({"ranked": "10 40", "x2": 7.0}, r"not the run's proposal .*\(0, 0, 7, 5\) vs"),
        ({"ranked": "10 10"}, "repeats a frame"),
    ],
)
def test_each_error_of_spec_12_names_the_file_the_count_and_a_row(
    tmp_path: Path, row: dict, message: str
) -> None:
    path = _csv(tmp_path, [row])
    with pytest.raises(RetrievalError, match=message) as err:
        _rank(path)
    text = str(err.value)
    assert text.startswith(f"{path}: 1 row ") and "(e.g. line 2" in text


def test_duplicates_and_the_distance_column(tmp_path: Path) -> None:
    path = _csv(tmp_path, [{"ranked": "10 40"}, {"ranked": "40 10"}])
    with pytest.raises(RetrievalError, match=r"1 row repeat a query subimage .*line 3: A/c/1"):
        _rank(path)
    path = _csv(tmp_path, [{"ranked": "10 40", "distance": 0.3}])
    with pytest.raises(RetrievalError, match=r"'distance' is not read .*give 'scores'"):
        _rank(path)
    sims = _csv(tmp_path, [{"ranked": "10 40", "scores": "1.5 0.2"}])
    with pytest.raises(RetrievalError, match=r"similarities outside \[0, 1\]"):
        _rank(sims, kind="similarity")


def test_parquet_lists_none_and_unreadable_files(tmp_path: Path) -> None:
    df = pd.read_csv(_csv(tmp_path, [{"ranked": "x"}]))
    df["ranked"] = [[10, 40, 30]]
    df["scores"] = [[0.1, 0.2, 0.2]]
    df.to_parquet(tmp_path / "r.parquet")
    out = _rank(tmp_path / "r.parquet")
    assert out["rank"][0] == 2 and out["d"][0] == pytest.approx(0.2)
    df["ranked"] = [None]
    df.to_parquet(tmp_path / "none.parquet")
    with pytest.raises(RetrievalError, match=r"none.parquet: 1 row have a 'ranked' that is not"):
        _rank(tmp_path / "none.parquet")
    (tmp_path / "bad.parquet").write_bytes(b"not parquet")
    with pytest.raises(RetrievalError, match="not a readable parquet file"):
        read_import(tmp_path / "bad.parquet")
    (tmp_path / "latin.csv").write_bytes("q_session\n\xe9t\xe9\n".encode("latin-1"))
    with pytest.raises(RetrievalError, match="not a UTF-8 CSV"):
        read_import(tmp_path / "latin.csv")
    with pytest.raises(RetrievalError, match="is a directory"):
        read_import(tmp_path)


def test_import_names() -> None:
    assert parse_import_arg("bovw=/x/ranks.csv").name == "bovw"
    spec = parse_import_arg("/x/my-netvlad.parquet")
    assert spec.name == "my-netvlad" and spec.path == Path("/x/my-netvlad.parquet")
    with pytest.raises(RetrievalError, match="localizer name"):
        parse_import_arg("bad name=/x/r.csv")

"""Bring your own localizer, end to end, as a user types it (issue 22, method §12).

``harness task export`` -> the user's code (the README's worked example, ``examples/``) ->
``harness reproduce --import NAME=FILE`` -> tables and ``report.html`` naming the localizer. An
imported list equal to the built-in engine's output reproduces the built-in ranks, ``d`` and
tables exactly.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from harness.cli import main

from ..conftest import ROOT, one_error
from ..readme_text import manual_text

FIXTURE_TOML = ROOT / "datasets" / "fixture.toml"
EXAMPLE = ROOT / "examples" / "hsv_localizer.py"


_err = one_error


def _seeded(local_run: tuple, out: Path) -> list[str]:
    """A new run directory holding a copy of the fixture run's cache (nothing recomputed), and the
    fixture's config without its figures beside it (no test here reads them; the page is still
    written, and no cache key holds ``[report]``)."""
    p, _, run = local_run
    shutil.copytree(run / "cache", out / "cache")
    shutil.copy(run / ".dbl-harness.json", out / ".dbl-harness.json")
    text = FIXTURE_TOML.read_text().replace('"annotations/', f'"{ROOT}/annotations/')
    text = text.replace('"datasets/models"', f'"{ROOT}/datasets/models"')
    cfg = out.parent / "fixture-no-figures.toml"
    cfg.write_text(text.replace("[report]\n", "[report]\nplots = false\n", 1))
    return ["--config", str(cfg), "--data-root", str(p.cfg.data_root), "--out", str(out)]


@pytest.fixture(scope="module")
def exported(local_run: tuple, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str]]:
    out = tmp_path_factory.mktemp("byo") / "run"
    args = _seeded(local_run, out)
    assert main(["task", "export", *args]) == 0
    return out, args


def test_task_export_lists_exactly_the_subimages_ranking_scores(
    local_run: tuple, exported: tuple[Path, list[str]]
) -> None:
    _, rec, run = local_run
    out, _ = exported
    q = pd.read_parquet(out / "task" / "queries.parquet")
    ranks = pd.read_parquet(run / "ranks.parquet")
    key = ["q_session", "q_camera", "q_utime", "r_session", "proposal_method", "box_id"]
    assert q.duplicated(key).sum() == 0
    got = set(map(tuple, q[key].to_numpy().tolist()))
    assert got == set(map(tuple, ranks[key].to_numpy().tolist()))  # every rank row, nothing more
    box = q.merge(ranks, on=key, suffixes=("", "_r"))
    for c in ("x1", "y1", "x2", "y2"):
        assert (box[c] == box[c + "_r"]).all()
    # the same proposal entries as the run (one cache key per session)
    task = json.loads((out / "task" / "task.json").read_text())
    assert sorted(task["keys"]["proposals"].values()) == sorted(rec["cache_entries"]["proposals"])
    # every image opens upright with cv2.imread, boxes inside it; the NCLT session is rotated
    refs = pd.read_parquet(out / "task" / "references.parquet")
    for df in (q.drop_duplicates("image"), refs.drop_duplicates("image").head(20)):
        for r in df.itertuples():
            img = cv2.imread(r.image)
            assert img is not None and img.shape[:2] == (r.height, r.width), r.image
    nclt = q[q["q_session"] == "2012-01-22"]["image"].iloc[0]
    assert nclt.startswith(str(out / "task" / "images"))
    # the database sizes are the L of a complete list
    dbs = pd.read_csv(out / "task" / "databases.csv")
    n = refs.groupby(["session", "proposal_method"])["utime"].nunique()
    assert {(r.r_session, r.proposal_method): r.frames for r in dbs.itertuples()} == n.to_dict()


def test_the_readme_example_is_the_example_file() -> None:
    readme = manual_text()
    block = re.search(r"```python\n(\"\"\"A localizer of your own.*?)```", readme, re.S)
    assert block, "the README's worked example is missing"
    assert block.group(1) == EXAMPLE.read_text()


def test_import_a_users_localizer_through_the_report_page(
    exported: tuple[Path, list[str]], capsys: pytest.CaptureFixture, tmp_path: Path
) -> None:
    out, args = exported
    ranks_csv = tmp_path / "hsv.csv"
    run = subprocess.run(
        [sys.executable, str(EXAMPLE), str(out / "task"), str(ranks_csv)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    capsys.readouterr()
    # the README's `harness rank --config FILE --out DIR --import NAME=FILE` first: the ranks alone
    assert main(["rank", *args, "--import", f"hsv={ranks_csv}"]) == 0
    said = capsys.readouterr().out
    ranked = pd.read_parquet(out / "ranks.parquet")
    assert f"{len(ranked)} ranked query subimages -> {out / 'ranks.parquet'}" in said
    assert set(ranked["localizer"]) == {"hsv"} and ranked["rank"].between(1, ranked["L"]).all()
    assert main(["reproduce", *args, "--import", f"hsv={ranks_csv}"]) == 0
    printed = capsys.readouterr().out
    assert "Localization quality of hsv" in printed and "localizer hsv" in printed
    html = (out / "report.html").read_text()
    assert "<title>dbl-harness report: fixture, localizer hsv</title>" in html
    assert "imported from " + str(ranks_csv) in html
    for stem in ("localization", "table1", "tableS", "tableP"):
        assert "(localizer: hsv)" in (out / f"{stem}.md").read_text().splitlines()[0]
    rec = json.loads((out / "run.json").read_text())
    assert rec["localizers"][0]["name"] == "hsv" and rec["localizers"][0]["kind"] == "import"
    assert rec["counts"]["unranked_query_images"] == 0
    split = pd.read_parquet(out / "splits" / "roc_max_0.05.parquet")
    assert set(split["localizer"]) == {"hsv"} and "loc_score_max" in split.columns
    summary = pd.read_parquet(out / "splits" / "summary.parquet")
    assert set(summary["localizer"]) == {"hsv"}
    # the localizer works (better than chance) and was scored on every query image
    loc = pd.read_csv(out / "localization.csv")
    row = loc[(loc["proposal_method"] == "all") & (loc["season_pair"] == "all")].iloc[0]
    assert row["recall_at_1"] > 2 * row["chance_recall_at_1"]

    # the same lists as parquet without scores: no d, so no score methods, and the tables say so
    pq_path = tmp_path / "hsv-order.parquet"  # a bare FILE: named after its stem
    df = pd.read_csv(ranks_csv).drop(columns=["scores"])
    df["ranked"] = [[int(v) for v in s.split()] for s in df["ranked"]]
    df.to_parquet(pq_path)
    capsys.readouterr()
    assert main(["reproduce", *args, "--import", str(pq_path)]) == 1
    err = _err(capsys)
    assert "holds the tables of localizer hsv; this run measures hsv-order" in err  # both
    assert "--force" in err
    assert main(["reproduce", *args, "--import", str(pq_path), "--force"]) == 0
    assert (
        "score_max, score_sum not computed: localizer hsv-order gives ranked lists"
        in (out / "tableS.md").read_text()
    )
    assert "score max" not in (out / "table1.csv").read_text().lower()
    assert (out / "report.html").exists()
    assert main(["report", str(out)]) == 0  # the page of an imported run rebuilds too


def test_every_query_image_must_be_ranked_unless_allowed(
    exported: tuple[Path, list[str]], capsys: pytest.CaptureFixture, tmp_path: Path
) -> None:
    out, args = exported
    q = pd.read_parquet(out / "task" / "queries.parquet")
    refs = pd.read_parquet(out / "task" / "references.parquet")
    frames = {s: sorted(set(g["utime"])) for s, g in refs.groupby("session")}
    q["ranked"] = [frames[s] for s in q["r_session"]]  # every frame, in time order
    q["L"] = [len(frames[s]) for s in q["r_session"]]
    first = q.iloc[0]
    img = (q["q_utime"] == first.q_utime) & (q["r_session"] == first.r_session)
    q[~img].to_parquet(tmp_path / "time.parquet")
    argv = ["reproduce", *args, "--import", f"time={tmp_path / 'time.parquet'}", "--force"]
    assert main(argv) == 1
    err = _err(capsys)
    assert "localizer 'time' ranks no subimage of 1 of" in err
    assert f"{first.q_session}/{first.q_camera}/{first.q_utime} -> {first.r_session}" in err
    allow = tmp_path / "allow.toml"
    text = FIXTURE_TOML.read_text().replace('"annotations/', f'"{ROOT}/annotations/')
    text = text.replace('"datasets/models"', f'"{ROOT}/datasets/models"')
    allow.write_text(text + "\n[import]\nallow_unranked_images = true\n")
    argv[argv.index("--config") + 1] = str(allow)
    assert main(argv) == 0
    assert "1 of " in (out / "table1.md").read_text()
    assert json.loads((out / "run.json").read_text())["counts"]["unranked_query_images"] == 1


def _builtin_lists(run: Path) -> pd.DataFrame:
    """The built-in engine's complete ranked lists with their distances, from its descriptors.

    For every rank row: every frame of the method's database, sorted by the exact L2 distance of
    its nearest subimage (float64 differences), with that distance as the score.
    """
    ranks = pd.read_parquet(run / "ranks.parquet")
    desc = {}
    for d in (run / "cache" / "descriptors").iterdir():
        idx = pd.read_parquet(d / "index.parquet")
        desc[idx["session"].iloc[0]] = (idx, np.load(d / "desc.npy").astype(np.float64))
    rows = []
    for (qs, rs, m), g in ranks.groupby(["q_session", "r_session", "proposal_method"], sort=True):
        qidx, qd = desc[qs]
        ridx, rd = desc[rs]
        sel = (ridx["proposal_method"] == m).to_numpy()
        db, frame = rd[sel], ridx["utime"].to_numpy()[sel]
        qrow = qidx.reset_index().set_index(["camera", "utime", "proposal_method", "box_id"])[
            "index"
        ]
        for r in g.itertuples():
            v = qd[qrow[(r.q_camera, r.q_utime, m, r.box_id)]]
            dist = np.sqrt(((db - v) ** 2).sum(1))
            per = pd.Series(dist, index=frame).groupby(level=0).min().sort_values(kind="stable")
            rows.append(
                {
                    "q_session": r.q_session,
                    "q_camera": r.q_camera,
                    "q_utime": r.q_utime,
                    "proposal_method": m,
                    "box_id": r.box_id,
                    "x1": r.x1,
                    "y1": r.y1,
                    "x2": r.x2,
                    "y2": r.y2,
                    "r_session": rs,
                    "ranked": per.index.to_numpy(np.int64),
                    "scores": per.to_numpy(),
                    "L": len(per),
                }
            )
    return pd.DataFrame(rows)


def test_an_import_of_the_builtin_engines_lists_reproduces_its_ranks_and_tables(
    local_run: tuple, tmp_path: Path
) -> None:
    _, _, run = local_run
    lists = _builtin_lists(run)
    lists.to_parquet(tmp_path / "builtin.parquet")
    out = tmp_path / "o"
    args = _seeded(local_run, out)
    assert main(["reproduce", *args, "--import", f"copy={tmp_path / 'builtin.parquet'}"]) == 0
    key = ["q_session", "q_camera", "q_utime", "r_session", "proposal_method", "box_id"]
    want = pd.read_parquet(run / "ranks.parquet").set_index(key).sort_index()
    got = pd.read_parquet(out / "ranks.parquet").set_index(key).sort_index()
    assert got.index.equals(want.index)
    for c in ("rank", "L", "place_size", "exact"):
        np.testing.assert_array_equal(got[c].to_numpy(), want[c].to_numpy(), err_msg=c)
    np.testing.assert_array_equal(got["d"].to_numpy(), want["d"].to_numpy())
    for stem in ("table1", "tableS", "tableP", "localization"):
        assert (out / f"{stem}.csv").read_bytes() == (run / f"{stem}.csv").read_bytes(), stem


def test_task_export_with_images_source_names_the_stored_files_and_their_rotation(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    out = tmp_path / "run"
    args = _seeded(local_run, out)
    assert main(["task", "export", *args, "--images", "source"]) == 0
    n = len(pd.read_parquet(local_run[2] / "ranks.parquet"))
    assert f"task: {n} query subimages" in capsys.readouterr().out
    q = pd.read_parquet(out / "task" / "queries.parquet")
    assert not (out / "task" / "images").exists()  # nothing written: the stored files are named
    nclt = q[q["q_session"] == "2012-01-22"].iloc[0]
    assert nclt["image"].endswith(".tiff") and nclt["rotation"] == "cw"
    stored = cv2.imread(nclt["image"])
    assert stored.shape[:2] == (nclt["width"], nclt["height"])  # sideways as stored
    upright = cv2.rotate(stored, cv2.ROTATE_90_CLOCKWISE)
    assert upright.shape[:2] == (nclt["height"], nclt["width"])
    assert set(q.loc[q["q_session"] != "2012-01-22", "rotation"]) == {"none"}


def test_lists_cut_before_their_place_make_bounds_said_in_a_warning_and_table_l(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """Issue 50's adversarial check: lists truncated so that they never hold the true place (a
    list of one where it ranks first) give bounds, not ranks: one WARNING line on the console with
    the count and share, and Table L (markdown, page) marks that localizer's row ``[bounds]``."""
    _, _, run = local_run
    key = ["q_session", "q_camera", "q_utime", "r_session", "proposal_method", "box_id"]
    lists = _builtin_lists(run).merge(
        pd.read_parquet(run / "ranks.parquet")[[*key, "rank"]], on=key
    )
    cut = [r[: max(int(k) - 1, 1)] for r, k in zip(lists["ranked"], lists["rank"], strict=True)]
    lists["scores"] = [s[: len(r)] for s, r in zip(lists["scores"], cut, strict=True)]
    lists["ranked"] = cut
    lists.drop(columns="rank").to_parquet(tmp_path / "cut.parquet")
    bounds, total = int((lists["rank"] > 1).sum()), len(lists)
    out = tmp_path / "o"
    args = _seeded(local_run, out)
    # the README's several-localizers config, its autoencoder beside the cut lists (Table L)
    multi = (ROOT / "datasets" / "fixture-localizers.toml").read_text()
    multi = (  # its localizers after the autoencoder left out, its [report] (200 resamples) kept
        multi[: multi.index('[[localizers]]\nname = "bovw')] + multi[multi.index("[report]") :]
    ).replace("[report]\n", "[report]\nplots = false\n", 1)  # no test here reads the figures
    multi = multi.replace('"annotations/', f'"{ROOT}/annotations/').replace(
        '"datasets/models"', f'"{ROOT}/datasets/models"'
    )
    cfg, lists_file = tmp_path / "cut.toml", tmp_path / "cut.parquet"
    cfg.write_text(f'{multi}\n[[localizers]]\nname = "cut"\nimport = {{ file = "{lists_file}" }}\n')
    args[args.index("--config") + 1] = str(cfg)
    assert main(["reproduce", *args]) == 0
    printed = " ".join(capsys.readouterr().out.split())  # the console wraps long log lines
    line = f"{bounds} of {total} query subimages ({100 * bounds / total:.0f}%) of localizer cut"
    assert printed.count(line) == 1, printed[-3000:]
    assert "WARNING" in printed.split(line)[0][-30:]
    share = 100 * (
        1 - pd.read_parquet(out / "ranks.parquet").query("localizer == 'cut'")["exact"].mean()
    )
    md = (out / "tableL.md").read_text()
    assert f"| cut [bounds: {share:.0f}%] |" in md and "computed on bounds, not ranks" in md
    assert "| autoencoder |" in md  # the exact localizer is not marked
    page = (out / "report.html").read_text()
    assert 'data-bounds="L"' in page and "cut [bounds:" in page

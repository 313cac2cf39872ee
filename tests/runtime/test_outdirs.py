"""Ownership by content (issue 26, item 1): the harness deletes or replaces only what it wrote.

Each case goes through the CLI as a user types it: a user's file inside an earlier output, under
``cache/``, or named like a temporary is never touched, and names from the config never escape
``--out``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.cli import main
from harness.fixture import writers as W
from harness.records import Pose
from harness.runtime.outdirs import is_temp_name, run_lock

from ..conftest import ROOT, one_error

FIXTURE_TOML = ROOT / "datasets" / "fixture.toml"
TINY = ["--frames", "6", "--width", "32", "--height", "40", "--loop-scale", "1.0"]


_err = one_error


def _mcap(tmp: Path) -> Path:
    rgb = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(4)]
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(8)]
    W.write_mcap(tmp / "log.mcap", frames, poses)
    return tmp / "log.mcap"


def test_force_refuses_over_a_users_file_inside_an_earlier_output(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    log = _mcap(tmp_path)
    out = tmp_path / "ingested"
    assert main(["ingest", str(log), "--session", "S", "--out", str(out)]) == 0
    capsys.readouterr()
    (out / "my_notes.txt").write_text("keep")
    assert main(["ingest", str(log), "--session", "S", "--out", str(out), "--force"]) == 1
    err = _err(capsys)
    assert "'my_notes.txt'" in err and "did not write" in err
    assert (out / "my_notes.txt").read_text() == "keep"
    (out / "my_notes.txt").unlink()  # once the user's file is out, --force replaces its own
    assert main(["ingest", str(log), "--session", "S", "--out", str(out), "--force"]) == 0

    fx = tmp_path / "fx"
    assert main(["fixture", "--out", str(fx), *TINY]) == 0
    capsys.readouterr()
    (fx / "truth" / "mine.csv").write_text("keep")
    assert main(["fixture", "--out", str(fx), *TINY, "--force"]) == 1
    assert "'truth/mine.csv'" in _err(capsys)
    assert (fx / "truth" / "mine.csv").read_text() == "keep"


def test_annotations_export_force_keeps_a_users_file(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    p, _, run = local_run
    pairs = next((run / "cache" / "pairs").glob("*/pairs.parquet"))
    df = pd.read_parquet(next((run / "cache" / "frames").glob("*/frames.parquet")))
    df["image"] = (
        df["image"]
        .str.replace("{data_root}", str(p.cfg.data_root), regex=False)
        .str.replace("{out}", str(run), regex=False)
    )
    frames = tmp_path / "frames.parquet"
    df.to_parquet(frames)
    out = tmp_path / "task"
    argv = ["annotations", "export", "--pairs", str(pairs), "--frames", str(frames)]
    assert main([*argv, "--out", str(out), "--limit", "2"]) == 0
    capsys.readouterr()
    (out / "labels_in_progress.json").write_text("{}")
    assert main([*argv, "--out", str(out), "--limit", "2", "--force"]) == 1
    assert "'labels_in_progress.json'" in _err(capsys)
    assert (out / "labels_in_progress.json").read_text() == "{}"


def test_force_refuses_an_output_whose_marker_lists_no_files(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """An output of an older version (marker without a file list): --force cannot tell."""
    log = _mcap(tmp_path)
    out = tmp_path / "ingested"
    assert main(["ingest", str(log), "--session", "S", "--out", str(out)]) == 0
    capsys.readouterr()
    (out / ".dbl-harness.json").write_text(json.dumps({"kind": "ingest", "owner": "dbl-harness"}))
    assert main(["ingest", str(log), "--session", "S", "--out", str(out), "--force"]) == 1
    assert "older version" in _err(capsys) and (out / "frames.parquet").exists()


def test_the_temporaries_sweep_touches_only_the_harness_own(
    local_run: tuple, tmp_path: Path
) -> None:
    _, _, run = local_run
    out = tmp_path / "o"
    shutil.copytree(run, out, ignore=shutil.ignore_patterns("cache"))
    user = [out / ".draft.tmp", out / "report" / ".notes.old-3", out / ".x.abcdefgh.tmp"]
    for f in user:
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text("mine")
    ours = out / ".table1.csv.dbl-harness-k2j4_x9q.tmp"
    ours.write_text("half")
    old = out / "cache" / "model" / ".abc.dbl-harness-old-4242"
    old.mkdir(parents=True)
    (old / "autoencoder.pt").write_bytes(b"\0")
    with run_lock(out):
        pass
    assert all(f.read_text() == "mine" for f in user)
    assert not ours.exists() and not old.exists()
    assert not is_temp_name(".draft.tmp") and is_temp_name(".a.dbl-harness-abcdefgh.tmp")


def test_gc_leaves_a_users_directories_and_links_under_cache_alone(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    _, _, run = local_run
    out = tmp_path / "o"
    shutil.copytree(run, out)
    mine = out / "cache" / "samples" / "my_experiment"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "big.bin").write_bytes(b"\0" * 10)
    (out / "cache" / "ranks" / "link").symlink_to(elsewhere, target_is_directory=True)
    (out / "cache" / "linked_stage").symlink_to(elsewhere, target_is_directory=True)
    # a harness entry into which a user saved a file: kept too
    entry = next(p for p in (out / "cache" / "pairs").iterdir())
    stale = out / "cache" / "pairs" / "0123456789abcdef"
    shutil.copytree(entry, stale)
    man = json.loads((stale / "manifest.json").read_text())
    (stale / "manifest.json").write_text(json.dumps({**man, "key": stale.name}))
    (stale / "mine.txt").write_text("keep")
    assert main(["gc", str(out)]) == 0
    text = capsys.readouterr().out
    assert "left alone (not written by the harness): cache/samples/my_experiment" in text
    assert "cache/ranks/link (a symbolic link)" in text and "'mine.txt'" in text
    assert (mine / "notes.txt").read_text() == "keep" and (elsewhere / "big.bin").exists()
    assert (stale / "mine.txt").exists()


def test_gc_and_report_on_a_damaged_run_json_are_one_error_line(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    _, _, run = local_run
    out = tmp_path / "o"
    shutil.copytree(run, out, ignore=shutil.ignore_patterns("cache"))
    (out / "run.json").write_text('{"cache_entries": ')
    assert main(["gc", str(out)]) == 1
    assert "run.json: unreadable" in _err(capsys)
    assert main(["report", str(out)]) == 1
    assert "run.json: unreadable" in _err(capsys)


@pytest.mark.parametrize("name", ["../x", "a/b", ".hidden", "..", ""])
def test_names_from_the_config_never_escape_out(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    text = FIXTURE_TOML.read_text()
    assert 'name = "2012-01-22"' in text
    cfg = tmp_path / "c.toml"
    cfg.write_text(text.replace('name = "2012-01-22"', f'name = "{name}"', 1))
    out = tmp_path / "deep" / "o"
    assert main(["ingest", "--config", str(cfg), "--out", str(out)]) == 1
    assert "sessions[0] name" in _err(capsys)
    assert not (tmp_path / "deep").exists() and not (tmp_path / "x").exists()
    log = _mcap(tmp_path)
    assert main(["ingest", str(log), "--session", name, "--out", str(out)]) == 1
    assert "--session" in _err(capsys)

"""Output directories and files: nothing foreign replaced, nothing partial left, resumes.

Nothing lost, nothing silently wrong: each case goes through the CLI as a user types it where it
can; bad input gives one ``ERROR:`` line, exit 1, and leaves nothing partial behind.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import pandas as pd
import pytest

from harness.cli import main
from harness.errors import HarnessError
from harness.pipeline.chain import Pipeline

from ..conftest import no_figures
from ..safety_common import FIXTURE_TOML, TINY, _config, _err, _log


def test_fixture_generation_never_touches_an_existing_data_root(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    real = tmp_path / "x" / "ground_truth" / "groundtruth_2012-01-22.csv"
    real.parent.mkdir(parents=True)
    real.write_text("real\n")
    assert (
        main(
            [
                "pairs",
                "--config",
                str(FIXTURE_TOML),
                "--data-root",
                str(tmp_path / "x"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 1
    )
    err = _err(capsys)
    assert "data_root exists and holds no generated fixture" in err and "generate = false" in err
    assert real.read_text() == "real\n" and sorted(p.name for p in (tmp_path / "x").rglob("*")) == [
        "ground_truth",
        real.name,
    ]


def test_ingest_refuses_a_foreign_out_and_replaces_its_own_only_with_force(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    log = _log(tmp_path, "mcap")
    d = tmp_path / "d"
    d.mkdir()
    (d / "thesis.txt").write_text("keep")
    assert main(["ingest", str(log), "--session", "S", "--out", str(d)]) == 1
    assert "holds files the harness did not write (e.g. 'thesis.txt')" in _err(capsys)
    assert (d / "thesis.txt").read_text() == "keep" and sorted(p.name for p in d.iterdir()) == [
        "thesis.txt"
    ]
    out = tmp_path / "o"
    assert main(["ingest", str(log), "--session", "S", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["ingest", str(log), "--session", "S", "--out", str(out)]) == 1
    assert "pass --force" in _err(capsys)
    assert main(["ingest", str(log), "--session", "S", "--out", str(out), "--force"]) == 0
    capsys.readouterr()
    assert (
        main(["ingest", str(log), "--session", "S", "--out", str(d), "--force"]) == 1
    )  # --force never covers a foreign dir
    assert (d / "thesis.txt").read_text() == "keep"


def test_out_as_the_working_directory_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = _log(tmp_path, "mcap")
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.md").write_text("mine")
    monkeypatch.chdir(work)
    for out in (".", str(work), str(tmp_path)):
        assert main(["ingest", str(log), "--session", "S", "--out", out]) == 1
        assert "working directory" in _err(capsys)
    assert (work / "notes.md").read_text() == "mine" and log.exists()


def test_fixture_export_and_reproduce_refuse_foreign_directories(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    d = tmp_path / "d"
    d.mkdir()
    (d / "keep.txt").write_text("keep")
    assert main(["fixture", "--out", str(d), *TINY]) == 1
    _err(capsys)
    fx = tmp_path / "fx"
    assert main(["fixture", "--out", str(fx), *TINY]) == 0
    capsys.readouterr()
    assert main(["fixture", "--out", str(fx), *TINY]) == 1 and "--force" in _err(capsys)
    assert main(["fixture", "--out", str(fx), *TINY, "--force"]) == 0
    capsys.readouterr()
    frames = tmp_path / "frames.parquet"
    pd.DataFrame({"session": [], "camera": [], "utime": []}).to_parquet(frames)
    pairs = tmp_path / "pairs.parquet"
    pd.DataFrame({"q_session": [], "q_camera": [], "q_utime": []}).to_parquet(pairs)
    assert (
        main(
            [
                "annotations",
                "export",
                "--pairs",
                str(pairs),
                "--frames",
                str(frames),
                "--out",
                str(d),
            ]
        )
        == 1
    )
    _err(capsys)
    assert (
        main(["reproduce", "--config", str(FIXTURE_TOML), "--data-root", str(fx), "--out", str(d)])
        == 1
    )
    assert "never writes into such a directory" in _err(capsys)
    assert sorted(p.name for p in d.iterdir()) == ["keep.txt"]
    ann_out = tmp_path / "ann.csv"
    ann_out.write_text("precious\n")
    assert (
        main(["annotations", "import", "coco", str(tmp_path / "none.json"), "--out", str(ann_out)])
        == 1
    )
    assert "pass --force" in _err(capsys) and ann_out.read_text() == "precious\n"


def test_temporaries_of_a_killed_run_are_removed_and_the_lock_refuses_a_second_run(
    local_run: tuple, tmp_path: Path
) -> None:
    from harness.runtime.outdirs import run_lock

    p, _, out = local_run
    q = Pipeline(no_figures(p.cfg), tmp_path / "o")
    debris = tmp_path / "o" / "cache" / "model" / ".abc123.dbl-harness-x7y8z9ab.tmp"
    stray = tmp_path / "o" / ".table1.csv.dbl-harness-x1y2z3w4.tmp"
    with run_lock(
        tmp_path / "o"
    ):  # another run holds the lock while a killed run's debris lies there
        debris.mkdir(parents=True)
        (debris / "train_crops.npy").write_bytes(b"\0" * 1000)
        stray.write_text("half")
        with pytest.raises(HarnessError, match=rf"another harness run \(pid {os.getpid()}\)"):
            q.run()
        assert debris.exists()  # nothing is removed while another run holds the lock
    shutil.copytree(out / "cache", tmp_path / "o" / "cache", dirs_exist_ok=True)
    q.run()
    assert not debris.exists() and not stray.exists()


def test_a_moved_run_directory_resumes_without_reading_the_old_place(
    local_run: tuple, tmp_path: Path
) -> None:
    p, _, out = local_run
    shutil.copytree(out, tmp_path / "first")
    shutil.move(str(tmp_path / "first"), str(tmp_path / "moved"))
    frames = pd.read_parquet(
        next((tmp_path / "moved" / "cache" / "frames").glob("*/frames.parquet"))
    )
    assert all(u.startswith(("{out}/", "{data_root}/")) for u in frames["image"])
    q = Pipeline(no_figures(p.cfg), tmp_path / "moved")
    q.run()
    assert sum(q.ran.values()) == 0
    assert (tmp_path / "moved" / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()


def test_a_hash_in_data_and_out_paths_works(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = _config(
        tmp_path, ("frames = 64\nwidth = 120\nheight = 160", "frames = 8\nwidth = 48\nheight = 64")
    )
    data, out = tmp_path / "da#ta", tmp_path / "ou#t"
    assert (
        main(["proposals", "--config", str(cfg), "--data-root", str(data), "--out", str(out)]) == 0
    )
    assert "edges" in capsys.readouterr().out


def test_a_rerun_with_fewer_splits_removes_stale_split_files(
    local_run: tuple, tmp_path: Path
) -> None:
    p, _, out = local_run
    shutil.copytree(out, tmp_path / "o", dirs_exist_ok=True)
    cfg = dataclasses.replace(p.cfg, splits=dataclasses.replace(p.cfg.splits, roc_max=(0.01, 0.05)))
    Pipeline(cfg, tmp_path / "o").run()
    assert sorted(f.name for f in (tmp_path / "o" / "splits").glob("roc_max_*")) == [
        "roc_max_0.01.parquet",
        "roc_max_0.05.parquet",
    ]
    assert sorted(f.name for f in (tmp_path / "o" / "plots").glob("pr_*")) == [
        "pr_roc_max_0.01.png",
        "pr_roc_max_0.05.png",
    ]
    assert pd.read_csv(tmp_path / "o" / "table1.csv").columns.tolist() == ["fusion", "0.01", "0.05"]


def test_outputs_take_their_mode_from_the_umask(local_run: tuple) -> None:
    from harness.runtime.cache import _UMASK

    _, _, out = local_run
    for f in ("table1.csv", "splits/summary.parquet", "run.json"):
        assert (out / f).stat().st_mode & 0o777 == 0o666 & ~_UMASK, f
    assert (out / "splits").stat().st_mode & 0o777 == 0o777 & ~_UMASK
    entry = next((out / "cache" / "ranks").iterdir())
    assert entry.stat().st_mode & 0o777 == 0o777 & ~_UMASK


def test_a_held_lock_names_its_holder_in_words_never_pid_unknown(tmp_path: Path) -> None:
    """A lock taken but with no pid written yet (the holder is starting), and a lock whose writer
    has exited while a process it started still holds it: each said as such, not "pid unknown"."""
    import subprocess
    import sys

    from harness.runtime.outdirs import LOCK, run_lock

    holder = (
        "import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "os.ftruncate(fd, 0)\n"
        "if len(sys.argv) > 2: os.pwrite(fd, (sys.argv[2] + '\\n').encode(), 0)\n"
        "print('held', flush=True)\n"
        "time.sleep(60)\n"
    )
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        text=True,
        capture_output=True,
        check=True,
    )
    dead_pid = gone.stdout.strip()  # a pid that has exited (reuse within the test: negligible)
    for extra, words in (
        ([], r"another harness run \(starting up: its pid is not written yet\)"),
        ([dead_pid], rf"a process started by harness run pid {dead_pid} \(which has exited\)"),
    ):
        d = tmp_path / f"o{len(extra)}"
        d.mkdir()
        proc = subprocess.Popen(
            [sys.executable, "-c", holder, str(d / LOCK), *extra], stdout=subprocess.PIPE, text=True
        )
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
            with pytest.raises(HarnessError, match=words) as ei, run_lock(d):
                pass
            assert "unknown" not in str(ei.value)
        finally:
            proc.kill()
            proc.wait()
    with run_lock(tmp_path / "o0"):  # the holder gone, the lock is free again, and ours
        assert (tmp_path / "o0" / LOCK).read_text() == f"{os.getpid()}\n"

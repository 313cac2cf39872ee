"""The maintainers' tools as typed: ``tools/compare_outputs.py`` and ``tools/walk.py``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from .conftest import ROOT

COMPARE = ROOT / "tools" / "compare_outputs.py"


def _run(before: Path, after: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(COMPARE), str(before), str(after)], capture_output=True, text=True
    )


def _outputs(root: Path, ap: float, key: str, seconds: float) -> None:
    run = root / "run"
    (run / "cache" / key).mkdir(parents=True)
    (run / "cache" / key / "x.bin").write_bytes(bytes([int(seconds)]))  # the cache: left out
    rec = {"table_d": [{"ap50": ap}], "entry": key, "path": str(run / "a.png"),
           "timings_s": {"detect": seconds}}  # fmt: skip
    (run / "detect.json").write_text(json.dumps(rec))
    (run / "report.html").write_text(
        f"<table><tr><td>time</td><td>{seconds} s</td></tr><tr><td>AP</td><td>{ap}</td></tr>"
    )


def test_outputs_that_differ_only_in_times_keys_and_paths_are_the_same(tmp_path: Path) -> None:
    _outputs(tmp_path / "a", 0.25, "0123456789abcdef", 3.0)
    _outputs(tmp_path / "b", 0.25, "fedcba9876543210", 4.0)
    got = _run(tmp_path / "a", tmp_path / "b")
    assert got.returncode == 0 and "2 files the same, 0 differ" in got.stdout, got.stdout


def test_a_figure_that_moved_is_named_with_its_field(tmp_path: Path) -> None:
    _outputs(tmp_path / "a", 0.25, "0123456789abcdef", 3.0)
    _outputs(tmp_path / "b", 0.26, "0123456789abcdef", 3.0)
    got = _run(tmp_path / "a", tmp_path / "b")
    assert got.returncode == 1
    assert "run/detect.json: /table_d[0]/ap50: '0.25' against '0.26'" in got.stdout, got.stdout
    assert "run/report.html: line 1" in got.stdout


def test_an_absent_or_empty_folder_is_one_error_line(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    for before in (tmp_path / "absent", tmp_path / "empty"):
        got = _run(before, tmp_path)
        lines = got.stderr.strip().splitlines()
        assert got.returncode == 1 and len(lines) == 1 and lines[0].startswith("ERROR: "), lines


def test_the_walk_follows_a_commands_arguments_through_the_files(tmp_path: Path) -> None:
    """``tools/walk.py``'s trace of ``harness detect`` on two folders that are not there (it stops
    at the config, quickly): the handler first, then each call that carries the arguments, the
    overrides or the config, in order, and the stays they make."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import walk
    finally:
        sys.path.remove(str(ROOT / "tools"))
    argv = ["detect", "--map-images", str(tmp_path / "a"), "--query-images", str(tmp_path / "b"),
            "--out", str(tmp_path / "out")]  # fmt: skip
    calls = walk.trace(argv)
    assert calls[:3] == [
        ("harness.cli.runs", "cmd_detect"),
        ("harness.cli.common", "check_executor_flags"),
        ("harness.cli.runs", "detect_sessions"),
    ], calls
    assert ("harness.config.assemble", "folders_config") in calls
    assert walk.stays(calls)[:3] == ["harness.cli.runs", "harness.cli.common", "harness.cli.runs"]
    assert not (tmp_path / "out").exists()  # it stopped before any work

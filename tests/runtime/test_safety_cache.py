"""The cache: disk full and read-only, memmaps, damaged entries rebuilt, keys follow the code.

Nothing lost, nothing silently wrong: each case goes through the CLI as a user types it where it
can; bad input gives one ``ERROR:`` line, exit 1, and leaves nothing partial behind.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from harness.cli import main
from harness.pipeline.chain import Pipeline

from ..conftest import no_figures
from ..safety_common import FIXTURE_TOML, _err


def test_disk_full_and_read_only_are_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    import harness.cli as cli

    for code, words in ((errno.ENOSPC, "free disk space"), (errno.EROFS, "read-only")):

        def boom(args: object, code: int = code) -> int:
            raise OSError(code, os.strerror(code), str(tmp_path / "o" / "cache" / "x"))

        monkeypatch.setattr(cli, "cmd_reproduce", boom)
        parser = cli.build_parser()
        monkeypatch.setattr(cli, "build_parser", lambda p=parser: p)
        for sp in parser._subparsers._group_actions[0].choices.values():  # type: ignore[union-attr]
            if sp.prog.endswith("reproduce"):
                sp.set_defaults(func=boom)
        assert main(["reproduce", "--config", str(FIXTURE_TOML), "--out", str(tmp_path / "o")]) == 1
        err = _err(capsys)
        assert str(tmp_path / "o" / "cache" / "x") in err and words in err


def test_memmaps_reserve_their_blocks(tmp_path: Path) -> None:
    """A training-crop or descriptor memmap is allocated up front (ENOSPC, not SIGBUS later)."""
    from harness.runtime.cache import open_memmap_reserved

    arr = open_memmap_reserved(tmp_path / "a.npy", np.uint8, (64, 64, 64, 3))
    assert os.stat(tmp_path / "a.npy").st_blocks * 512 >= 64 * 64 * 64 * 3
    del arr


def test_a_damaged_cache_entry_is_rebuilt(local_run: tuple, tmp_path: Path) -> None:
    p, _, out = local_run
    q = Pipeline(no_figures(p.cfg), tmp_path / "o")
    shutil.copytree(out / "cache", tmp_path / "o" / "cache", dirs_exist_ok=True)
    victim = next((tmp_path / "o" / "cache" / "samples").glob("*/samples.parquet"))
    victim.write_bytes(victim.read_bytes()[:100])
    q.run()
    assert q.ran.get("samples") == 1 and sum(v for k, v in q.ran.items() if k != "samples") == 0
    assert (tmp_path / "o" / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()


def test_stage_keys_change_with_the_code(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import harness
    import harness.runtime.cache as cache

    pkg = Path(harness.__file__).parent
    shutil.copytree(pkg, tmp_path / "harness", ignore=shutil.ignore_patterns("__pycache__"))
    before = cache.code_fingerprint(tmp_path / "harness")
    assert before == cache.CODE_FINGERPRINT  # the copy hashes like the installed package
    fusion = tmp_path / "harness" / "fusion" / "rules" / "base.py"
    fusion.write_text(
        fusion.read_text().replace(
            "cover.sum(1) * (cover * inv[None, :]).sum(1)",
            "(cover * inv[None, :]).sum(1)",
        )
    )
    after = cache.code_fingerprint(tmp_path / "harness")
    assert after != before
    # the report page is rebuilt on every run: no stage depends on it
    html = tmp_path / "harness" / "reports" / "html" / "page.py"
    html.write_text(html.read_text() + "\n# an edit\n")
    assert cache.code_fingerprint(tmp_path / "harness") == after
    sc = cache.StageCache(tmp_path / "c")
    k1 = sc.key("samples", "x")
    monkeypatch.setattr(cache, "CODE_FINGERPRINT", after)
    assert sc.key("samples", "x") != k1


def test_a_real_full_disk_mid_stage_is_one_error_line_and_the_rerun_resumes_to_the_same_tables(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """A small tmpfs as --out: the finished stages (ingest up to the model) fit, the descriptors do
    not. The run stops with one ERROR line; with space made (the tmpfs grown), the same command
    resumes and writes the local run's tables, byte for byte, with no temporary left."""
    import subprocess

    from ..conftest import one_error

    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a real full disk needs a tmpfs mount: run as root (CI runs as root)")
    p, _, run = local_run
    kept = ("ingest", "frames", "pairs", "proposals", "model")
    need = sum(
        f.stat().st_size for s in kept for f in (run / "cache" / s).rglob("*") if f.is_file()
    )
    mnt = tmp_path / "small"
    mnt.mkdir()
    size_kb = need // 1024 + 2048  # the finished stages and 2 MB: not the descriptors (7 MB)
    got = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(mnt)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if got.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {got.stderr.strip()}")
    try:
        out = mnt / "run"
        for s in kept:
            shutil.copytree(run / "cache" / s, out / "cache" / s)
        shutil.copy(run / ".dbl-harness.json", out / ".dbl-harness.json")
        argv = ["reproduce", "--config", str(FIXTURE_TOML), "--data-root", str(p.cfg.data_root)]
        argv += ["--out", str(out)]
        capsys.readouterr()
        assert main(argv) == 1
        err = one_error(capsys)
        assert "free disk space" in err, err
        assert not (out / "table1.csv").exists()
        subprocess.run(["mount", "-o", "remount,size=256m", str(mnt)], check=True)
        assert main(argv) == 0
        assert (out / "table1.csv").read_bytes() == (run / "table1.csv").read_bytes()
        assert (out / "tableS.csv").read_bytes() == (run / "tableS.csv").read_bytes()
        left = [f for f in out.rglob("*") if ".dbl-harness-" in f.name and f.name.endswith(".tmp")]
        assert not left, left
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)

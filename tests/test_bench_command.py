"""The README's bench command as a user types it: ``.venv/bin/python -m bench --quick --only CASE``.

Run in a copy of ``bench/`` (the command writes ``results/bench/`` beside the package it runs
from), so the repository's tracked figures are left as they are. The cheapest case stands for the
rest: the command line, a case in its own subprocess, ``bench.json`` and ``bench.md``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bench(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``python -m bench ARGS`` as a user types it in ``cwd``; it must succeed."""
    proc = subprocess.run(
        [sys.executable, "-m", "bench", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


def test_the_bench_command_runs_as_typed_and_keeps_other_cases_figures(tmp_path: Path) -> None:
    shutil.copytree(ROOT / "bench", tmp_path / "bench", ignore=shutil.ignore_patterns(".data"))
    (tmp_path / "datasets").mkdir()
    shutil.copy(ROOT / "datasets" / "fixture.toml", tmp_path / "datasets")  # the case reads it
    out = tmp_path / "results" / "bench"
    out.mkdir(parents=True)
    # a figure of another case, from an earlier run: --only keeps it
    earlier = {"case": "rank exact db=1000", "median": 1.0, "unit": "query subimages/s"}
    (out / "bench.json").write_text(json.dumps({"results": [{**earlier, "group": "ranking"}]}))
    tracked = (ROOT / "results" / "bench" / "bench.json").read_bytes()
    proc = _bench(tmp_path, "--quick", "--only", "fusion")
    assert "fusion: " in proc.stdout
    rows = json.loads((out / "bench.json").read_text())["results"]
    groups = {r["group"] for r in rows}
    assert groups == {"ranking", "fusion"}
    assert all(r["median"] > 0 for r in rows if r["group"] == "fusion")
    md = (out / "bench.md").read_text()
    assert "| rank exact db=1000 |" in md
    assert any(f"| {r['case']} |" in md for r in rows if r["group"] == "fusion")
    assert (ROOT / "results" / "bench" / "bench.json").read_bytes() == tracked
    fresh = [r for r in rows if r["group"] == "fusion"]
    assert all(r["date"][:4] >= "2026" and ("AVX" in r["cpu"]) for r in fresh), fresh[0]
    assert all(isinstance(r["cpu_flags"], list) for r in fresh), fresh[0]  # bf16 where it is
    # the copy is not a git checkout: its rows say so rather than claim a commit
    assert all(r["commit"] is None for r in fresh)
    assert "| rank exact db=1000 |" in md and "no commit recorded" in md
    # `python -m bench --render` as typed: bench.md again from bench.json, nothing run or written
    before = (out / "bench.json").read_bytes()
    (out / "bench.md").write_text("old")
    proc = _bench(tmp_path, "--render")
    assert (out / "bench.md").read_text() == md and (out / "bench.json").read_bytes() == before
    assert "result(s) in" not in proc.stdout  # no case ran


def test_a_bench_row_is_stale_once_the_code_it_measures_changes_after_its_commit() -> None:
    """Rows from the repository's own history: measured at HEAD (current unless the measured code
    is dirty), at the first commit (stale, naming the paths and the commit that changed them), and
    with no commit (said so)."""
    from bench.provenance import _git, code_changed, staleness

    head = _git("rev-parse", "HEAD")
    first = (_git("rev-list", "--max-parents=0", "HEAD") or "").splitlines()
    if head is None or not first or _git("rev-parse", "--is-shallow-repository") == "true":
        pytest.skip("needs the repository's git history (a full clone)")
    measures = ("harness/evaluate/metrics.py",)
    last = _git("log", "-1", "--format=%H", "--", *measures)
    assert last and last != first[0]
    assert staleness({"commit": head, "dirty": False}, measures) == ""
    assert staleness({"commit": head, "dirty": True}, measures).startswith("dirty")
    old = staleness({"commit": first[0]}, measures)
    assert old.startswith("stale: harness/evaluate/metrics.py changed in "), old
    # the commit named is the newest that changed the file's code; any later one changed words
    named = _git("rev-parse", old.split(" changed in ")[1][:8]) or ""
    assert code_changed(f"{named}^", measures, head=named)
    later = (_git("rev-list", f"{named}..HEAD", "--", *measures) or "").splitlines()
    assert not any(code_changed(f"{c}^", measures, head=c) for c in later)
    assert staleness({}, measures).startswith("stale? no commit recorded")


def test_a_change_to_docstrings_or_comments_alone_leaves_a_row_current() -> None:
    """A file's code is its syntax tree without docstrings: a re-wrapped docstring or a new
    comment is the same code, a changed statement is not; a file that is not Python is its text.
    From the history: a commit that only re-wrapped a bench case's docstring leaves the rows
    measured before it current."""
    from bench.provenance import _git, code_changed, code_of

    before = 'def f(x):\n    """Old words."""\n    return x + 1\n'
    assert code_of("a.py", before) == code_of("a.py", "def f(x):  # a comment\n    return x + 1\n")
    assert code_of("a.py", before) == code_of(
        "a.py", 'def f(x):\n    """New\n    words."""\n    return x + 1\n'
    )
    assert code_of("a.py", before) != code_of(
        "a.py", 'def f(x):\n    """Old words."""\n    return x + 2\n'
    )
    assert code_of("a.py", "def (") is None and code_of("a.toml", "k = 1") == "k = 1"
    rewrap = "c21a788"  # bench/cases/fixture_figures.py: its docstring wrapped at 100 columns
    parent = _git("rev-parse", f"{rewrap}^")
    if parent is None or _git("rev-parse", "--is-shallow-repository") == "true":
        pytest.skip("needs the repository's git history (a full clone)")
    changed = _git("diff", "--name-only", parent, rewrap) or ""
    assert changed.splitlines() == ["bench/cases/fixture_figures.py"]
    assert code_changed(parent, ("bench/cases/fixture_figures.py",), head=rewrap) == []
    first = (_git("rev-list", "--max-parents=0", "HEAD") or "").splitlines()
    assert "harness/evaluate/metrics.py" in code_changed(first[0], ("harness/evaluate",))
    assert _git("diff", "--quiet", parent, rewrap, "--", "bench/cases/fixture_figures.py") is None
    assert code_of("x.py", _git("show", f"{parent}:bench/cases/fixture_figures.py")) == code_of(
        "x.py", _git("show", f"{rewrap}:bench/cases/fixture_figures.py")
    )


def test_the_full_nclt_workload_reads_each_sessions_length_from_the_ground_truth(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With NCLT's ground truth at ``$BENCH_NCLT_ROOT`` the projection's trajectories are measured
    (the x-y path: 3-4-5 steps, z and the angles ignored); without it, or with a session missing,
    there is nothing to measure and the case says it assumed them."""
    from bench.cases.nclt_sessions import ENV, session_lengths, session_names

    names = session_names()
    assert names == ["2012-01-22", "2012-03-31", "2012-08-04", "2012-11-17"]
    gt = tmp_path / "ground_truth"
    gt.mkdir()
    for i, name in enumerate(names):
        rows = [f"{1000 * k},{3.0 * k},{4.0 * k},{0.1 * k},0,0,{0.01 * k}" for k in range(i + 2)]
        (gt / f"groundtruth_{name}.csv").write_text("\n".join(rows) + "\n")
    monkeypatch.setenv(ENV, str(tmp_path))
    assert session_lengths() == {name: 5.0 * (i + 1) for i, name in enumerate(names)}
    (gt / f"groundtruth_{names[-1]}.csv").unlink()
    assert session_lengths() is None
    monkeypatch.delenv(ENV)
    assert session_lengths() is None


def test_a_row_is_dirty_only_when_uncommitted_changes_alter_its_code(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """In a repository of its own: a new comment or docstring left uncommitted keeps a row's
    stamp clean; a changed statement, a new file or a removed one makes it dirty."""
    import bench.provenance as prov

    def git(*args: str) -> None:
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "m.py").write_text('def f():\n    """Words."""\n    return 1\n')
    git("add", "m.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "m")
    monkeypatch.setattr(prov, "ROOT", tmp_path)
    assert prov.stamp(("m.py",))["dirty"] is False
    (tmp_path / "m.py").write_text('def f():  # a comment\n    """Other words."""\n    return 1\n')
    assert prov.stamp(("m.py",))["dirty"] is False
    (tmp_path / "m.py").write_text("def f():\n    return 2\n")
    assert prov.stamp(("m.py",))["dirty"] is True
    git("checkout", "-q", "m.py")
    (tmp_path / "n.py").write_text("x = 1\n")
    assert prov.stamp((".",))["dirty"] is True
    (tmp_path / "n.py").unlink()
    (tmp_path / "m.py").unlink()
    assert prov.stamp(("m.py",))["dirty"] is True


def test_a_native_kernels_child_sheds_the_caps_its_parent_pinned(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A child started for ``HARNESS_KERNELS=native`` from a pinned process (every bench process
    is one) gets none of the pinned caps, keeps a cap the user set to another value, and on an
    AVX-512 CPU runs torch above AVX2; in the pinned process no bf16 figure is called native."""
    import harness.kernels as kernels
    from bench.cases.common import bf16_native, kernel_env

    pinned = kernels.caps(asked="avx2")
    for k, v in pinned.items():
        monkeypatch.setenv(k, v)
    # the user's own value, kept (faiss is not loaded by the children below)
    monkeypatch.setenv("FAISS_OPT_LEVEL", "generic")
    env = kernel_env("native")
    assert env[kernels.ENV] == "native"
    assert env.get("FAISS_OPT_LEVEL") == "generic"
    assert not [k for k, v in pinned.items() if env.get(k) == v]
    if pinned:  # x86-64 with AVX2: the caps are in force here, so bf16 is emulated
        assert bf16_native() is False
    code = "import harness, torch; print(torch.backends.cpu.get_cpu_capability())"
    level = {}
    for asked, child_env in (("native", env), ("avx2", kernel_env("avx2"))):
        proc = subprocess.run(
            [sys.executable, "-c", code], env=child_env, capture_output=True, text=True, check=True
        )
        level[asked] = proc.stdout.strip().splitlines()[-1]
    if "avx512f" in kernels.cpu_flags() and pinned:
        assert level == {"native": "AVX512", "avx2": "AVX2"}
    else:
        assert level["native"] == level["avx2"]

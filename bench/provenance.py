"""Where a bench row comes from, and whether the code it measured has changed since.

Every row ``python -m bench`` records carries ``commit`` (the checkout's HEAD), ``dirty`` (whether
the files the case measures had uncommitted changes), ``date`` (UTC, ISO 8601) and ``cpu`` (the
model name and the widest SIMD the CPU has: figures of one machine kind differ between AVX-512 and
AVX2-only instances) with ``cpu_flags`` (the flags a figure depends on, bf16 included).
``bench.md`` marks a row *stale* when a commit after the row's own changed the code its case
measures (:func:`bench.cases.measures`): a file's syntax tree without docstrings, so a change to
comments or docstrings alone does not make a row stale (:func:`code_changed`). It says so where a
row records no commit at all (rows from before this record).
"""

from __future__ import annotations

import datetime as dt
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    """``git args`` in the repository, its stdout stripped; None where git or history is missing."""
    try:
        proc = subprocess.run(
            ["git", *args], cwd=ROOT, capture_output=True, text=True, check=False, timeout=30
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


#: The CPU flags a figure depends on: the SIMD width, fused multiply-add, and the bf16 / int8
#: matrix instructions the encoder and ranking products could use.
RELEVANT_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_tile")


def cpu_flags() -> list[str]:
    """Which of :data:`RELEVANT_FLAGS` this CPU has (``harness.runtime.hardware.cpu_flags``)."""
    from harness.runtime.hardware import cpu_flags as flags

    have = flags()
    return [f for f in RELEVANT_FLAGS if f in have]


def cpu() -> str:
    """The CPU's model name and its widest SIMD (``AVX-512``, ``AVX2`` or ``no AVX2``)."""
    model, flags = "unknown CPU", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model == "unknown CPU":
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    simd = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    return f"{model} ({simd})"


def stamp(measures: tuple[str, ...]) -> dict[str, object]:
    """The provenance fields of a row measured now of code under ``measures``.

    ``dirty``: a file under ``measures`` differs from HEAD in its code (an uncommitted change to
    comments or docstrings alone leaves it clean, as :func:`code_changed` does a commit's).
    """
    status = _git("status", "--porcelain", "--untracked-files=all", "--", *measures)
    dirty = None if status is None else any(_uncommitted_code(line) for line in status.splitlines())
    return {
        "commit": _git("rev-parse", "HEAD"),
        "dirty": dirty,
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "cpu": cpu(),
        "cpu_flags": cpu_flags(),
    }


def _uncommitted_code(status_line: str) -> bool:
    """Whether the file of a ``git status --porcelain`` line differs from HEAD in its code."""
    name = status_line.split(maxsplit=1)[-1].split(" -> ")[-1].strip('"')
    path = ROOT / name
    now = path.read_text(errors="replace") if path.is_file() else None
    before = code_of(name, _git("show", f"HEAD:{name}"))
    return now is None or before is None or code_of(name, now) != before


def _last_code_change(since: str, measures: tuple[str, ...]) -> str | None:
    """The newest commit after ``since`` that changed the code under ``measures`` (not only its
    words), or None."""
    for c in (_git("rev-list", f"{since}..HEAD", "--", *measures) or "").splitlines():
        if code_changed(f"{c}^", measures, head=c):
            return c
    return None


def staleness(row: dict, measures: tuple[str, ...]) -> str:
    """ "" for a row measured at the last change of its code, else what makes it stale, in words."""
    commit = row.get("commit")
    if not commit:
        return "stale? no commit recorded (measured before rows carried one)"
    last = _git("log", "-1", "--format=%H", "--", *measures)
    if last is None:
        return "not checked: no git history here"
    if last and _git("merge-base", "--is-ancestor", last, commit) is None:
        changed = code_changed(commit, measures)
        if changed:
            last = _last_code_change(commit, measures) or last
            when = _git("log", "-1", "--format=%cs", last) or "?"
            return (
                f"stale: {', '.join(measures)} changed in {last[:8]} ({when}) after this row "
                f"({', '.join(changed[:3])}{' ...' if len(changed) > 3 else ''})"
            )
    return "dirty: measured with uncommitted changes" if row.get("dirty") else ""


def code_of(path: str, text: str | None) -> str | None:
    """What runs of a file: a Python file's code, any other file's text.

    The code has no docstrings or comments (:func:`harness.runtime.code.code_text`); None for a
    missing file or Python that does not parse.
    """
    from harness.runtime.code import code_text

    if text is None or not path.endswith(".py"):
        return text
    try:
        return code_text(text)
    except SyntaxError:
        return None


def code_changed(commit: str, measures: tuple[str, ...], head: str = "HEAD") -> list[str]:
    """The files under ``measures`` whose code differs between ``commit`` and ``head``.

    A change to docstrings or comments alone leaves a file's code as it was: a row measured
    before it still measures the code that runs now.
    """
    names = _git("diff", "--name-only", commit, head, "--", *measures)
    if names is None:
        return list(measures)
    out = []
    for n in names.splitlines():
        now = code_of(n, _git("show", f"{head}:{n}"))
        if now is None or now != code_of(n, _git("show", f"{commit}:{n}")):
            out.append(n)
    return out

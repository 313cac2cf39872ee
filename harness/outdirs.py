"""Output directories the harness may write into, the run lock, and clean-up of stale temporaries.

The harness never deletes or replaces a path it did not create. Every directory it writes
holds a marker file (:data:`MARKER`) naming the owner and the kind of output; a command that
would write into, or replace, a directory without that marker refuses with an error naming the
path and the flag to use. A run directory is locked for the duration of a run (one ``flock``
per ``--out``), so two runs never write into one directory at the same time; temporaries left
by a killed run are removed by the next run that holds the lock.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from .errors import HarnessError

log = logging.getLogger(__name__)

#: File that marks a directory as written by the harness.
MARKER = ".dbl-harness.json"
OWNER = "dbl-harness"
LOCK = ".dbl-harness.lock"


class OwnershipError(HarnessError):
    """An output path exists and was not written by the harness (or needs ``--force``)."""


def marker_text(kind: str) -> str:
    """The marker's content: deterministic, so a directory's bytes depend on its content alone."""
    return json.dumps({"owner": OWNER, "kind": kind}, sort_keys=True) + "\n"


def write_marker(directory: Path, kind: str) -> None:
    """Mark ``directory`` (which must exist) as the harness's own output of ``kind``."""
    (Path(directory) / MARKER).write_text(marker_text(kind))


def owner_kind(directory: Path) -> str | None:
    """The kind recorded in ``directory``'s marker, or None when it has no (readable) marker."""
    try:
        doc = json.loads((Path(directory) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return str(doc.get("kind")) if isinstance(doc, dict) and doc.get("owner") == OWNER else None


def _first_entry(directory: Path) -> str:
    with os.scandir(directory) as it:
        names = sorted(e.name for e in it)
    return names[0] if names else ""


def _is_empty_dir(path: Path) -> bool:
    return path.is_dir() and not _first_entry(path)


def _legacy_run_dir(path: Path) -> bool:
    """A run directory written by a version of the harness from before the marker existed."""
    try:
        rec = json.loads((path / "run.json").read_text())
    except (OSError, ValueError):
        return False
    return (
        isinstance(rec, dict)
        and "dbl-harness" in rec.get("versions", {})
        and (path / "cache").is_dir()
    )


def claim_dir(path: Path, kind: str, flag: str = "--out") -> Path:
    """Make ``path`` a directory the harness writes *into* (a run directory); returns it resolved.

    Absent or empty: created and marked. Marked with the same kind: used as it is (a rerun
    resumes there). Anything else is refused, whatever it holds.

    Raises:
        OwnershipError: ``path`` is a file, or a non-empty directory the harness did not write.
    """
    path = Path(path).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise OwnershipError(f"{path}: {flag} names an existing file; give a directory path")
    if path.is_dir():
        kind_found = owner_kind(path)
        if kind_found == kind:
            return path
        if kind_found is None and _legacy_run_dir(path) and kind == "run":
            write_marker(path, kind)
            return path
        if kind_found is not None:
            raise OwnershipError(
                f"{path}: holds a harness {kind_found} output, not a {kind}; choose another {flag}"
            )
        if not _is_empty_dir(path):
            raise OwnershipError(
                f"{path}: exists and holds files the harness did not write (e.g. "
                f"{_first_entry(path)!r}); "
                f"the harness never writes into such a directory: choose a new or empty {flag}"
            )
    path.mkdir(parents=True, exist_ok=True)
    write_marker(path, kind)
    return path


def check_replaceable(path: Path, kind: str, force: bool, flag: str = "--out") -> Path:
    """Check that ``path`` may be *replaced whole* by a new output of ``kind``; returns it resolved.

    Absent or an empty directory: fine. A directory marked as the harness's ``kind`` output:
    fine with ``force`` only. Anything else (a file, an unmarked or foreign directory, the
    working directory or one of its parents) is refused.

    Raises:
        OwnershipError: naming the path and the flag to use.
    """
    path = Path(path).expanduser().resolve()
    cwd = Path.cwd().resolve()
    if path == cwd or path in cwd.parents:
        raise OwnershipError(
            f"{path}: {flag} is the working directory or one of its parents; give a new path"
        )
    if not path.exists() or _is_empty_dir(path):
        return path
    if not path.is_dir():
        raise OwnershipError(
            f"{path}: {flag} names an existing file the harness did not write; give a new path"
        )
    found = owner_kind(path)
    if found is None:
        raise OwnershipError(
            f"{path}: exists and holds files the harness did not write (e.g. "
            f"{_first_entry(path)!r}); "
            f"it is never replaced: choose a new {flag}"
        )
    if found != kind:
        raise OwnershipError(
            f"{path}: holds a harness {found} output, not a {kind}; choose another {flag}"
        )
    if not force:
        raise OwnershipError(
            f"{path}: exists (a harness {kind} output); pass --force to replace it, or "
            f"choose a new {flag}"
        )
    return path


def check_file_replaceable(path: Path, force: bool, flag: str = "--out") -> Path:
    """A single output file: a new path, or an existing file only with ``force``."""
    path = Path(path).expanduser().resolve()
    if path.is_dir():
        raise OwnershipError(f"{path}: {flag} names a directory; give a file path")
    if path.exists() and not force:
        raise OwnershipError(f"{path}: exists; pass --force to replace it, or choose a new {flag}")
    return path


def is_temp_name(name: str) -> bool:
    """Names of the temporaries that :mod:`harness.cache` creates.

    Those are ``.<name>.<random>.tmp`` and ``.<name>.old-<pid>``.
    """
    return name.startswith(".") and (name.endswith(".tmp") or ".old-" in name)


def sweep_temporaries(root: Path) -> int:
    """Remove every harness temporary under ``root`` (call only while holding ``root``'s lock).

    Returns:
        How many entries were removed.
    """
    removed = 0
    if not Path(root).is_dir():
        return 0
    for dirpath, dirnames, filenames in os.walk(root):
        for name in list(dirnames):
            if is_temp_name(name):
                shutil.rmtree(Path(dirpath) / name, ignore_errors=True)
                dirnames.remove(name)
                removed += 1
        for name in filenames:
            if is_temp_name(name):
                with contextlib.suppress(FileNotFoundError):
                    (Path(dirpath) / name).unlink()
                removed += 1
    return removed


@contextlib.contextmanager
def run_lock(directory: Path) -> Iterator[None]:
    """Hold ``directory``'s run lock (exclusive, non-blocking) for the block.

    On entry, temporaries left by killed runs are removed (they are older than the lock).

    Raises:
        HarnessError: another process holds the lock (its pid is named).
    """
    directory = Path(directory)
    lock_path = directory / LOCK
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            raise HarnessError(
                f"{directory}: another harness run (pid {holder}) is writing into this directory; "
                "wait for it to finish, or choose another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        n = sweep_temporaries(directory)
        if n:
            log.info(
                "removed %d temporary entr%s left by an interrupted run under %s",
                n,
                "y" if n == 1 else "ies",
                directory,
            )
        yield
    finally:
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
        os.close(fd)  # releases the flock

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
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

from harness.errors import HarnessError, OwnershipError

log = logging.getLogger(__name__)

#: File that marks a directory as written by the harness.
MARKER = ".dbl-harness.json"
OWNER = "dbl-harness"
LOCK = ".dbl-harness.lock"


def marker_text(kind: str, entries: list[str] | None = None) -> str:
    """The marker's content: deterministic, so a directory's bytes depend on its content alone.

    Args:
        kind: The kind of output (``run``, ``ingest``, ``fixture``, ...).
        entries: The relative paths (files and directories) the harness wrote, for an output
            that is replaced whole with ``--force``; None for a directory written into (a run).
    """
    doc: dict[str, object] = {"owner": OWNER, "kind": kind}
    if entries is not None:
        doc["entries"] = sorted(entries)
    return json.dumps(doc, sort_keys=True) + "\n"


def _entries(directory: Path) -> list[str]:
    """Every path under ``directory`` (files and directories, not following links), relative."""
    out = []
    for dirpath, dirnames, filenames in os.walk(directory):
        base = Path(dirpath).relative_to(directory)
        out += [
            str(base / n)
            for n in dirnames + filenames
            if not (dirpath == str(directory) and n in (MARKER, LOCK))
        ]
    return sorted(out)


def write_marker(directory: Path, kind: str, record_entries: bool = False) -> None:
    """Mark ``directory`` (which must exist) as the harness's own output of ``kind``.

    With ``record_entries`` (call it last, when the output is complete), the marker lists every
    path the harness wrote there, so that a later ``--force`` replaces only those and refuses
    over anything a user added.
    """
    directory = Path(directory)
    entries = _entries(directory) if record_entries else None
    (directory / MARKER).write_text(marker_text(kind, entries))


def marker_entries(directory: Path) -> list[str] | None:
    """The entries a marker lists (None: no marker, or one that lists none)."""
    try:
        doc = json.loads((Path(directory) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    ent = doc.get("entries") if isinstance(doc, dict) else None
    return [str(e) for e in ent] if isinstance(ent, list) else None


def foreign_entries(directory: Path) -> list[str]:
    """Paths under a marked ``directory`` that its marker does not list (a user's files)."""
    listed = marker_entries(directory)
    if listed is None:
        return []
    known = set(listed)
    return [e for e in _entries(Path(directory)) if e not in known]


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


def read_run_record(out: Path) -> dict[str, object]:
    """The ``run.json`` of a finished run in ``out``, read and checked.

    Raises:
        HarnessError: No ``run.json`` there, or one that is not a JSON object (cut short,
            edited, not UTF-8): the message names the file and says how to rewrite it.
    """
    path = Path(out) / "run.json"
    if not path.exists():
        raise HarnessError(f"{out}: no run.json here; run `harness reproduce --out {out}` first")
    try:
        rec = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise HarnessError(
            f"{path}: unreadable ({type(err).__name__}: {err}); rerun `harness reproduce` into "
            f"{out} to rewrite it"
        ) from None
    if not isinstance(rec, dict) or not isinstance(rec.get("config"), dict):
        raise HarnessError(
            f"{path}: unreadable (not a run record: no 'config' object); rerun `harness "
            f"reproduce` into {out} to rewrite it"
        )
    return rec


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
    if marker_entries(path) is None:
        raise OwnershipError(
            f"{path}: a harness {kind} output written by an older version that did not list its "
            f"files, so --force cannot tell them from yours; move what you want to keep and "
            f"remove it yourself, or choose a new {flag}"
        )
    extra = foreign_entries(path)
    if extra:
        more = f" and {len(extra) - 1} more" if len(extra) > 1 else ""
        raise OwnershipError(
            f"{path}: holds {extra[0]!r}{more} that the harness did not write; --force would "
            f"delete it with the old output, so it refuses: move it out, or choose a new {flag}"
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


#: The signature in every temporary's name (see :func:`harness.runtime.cache.atomic_path`).
TEMP_TAG = "dbl-harness"
_TEMP = re.compile(r"^\..+\.dbl-harness-[A-Za-z0-9_]{8}\.tmp$|^\..+\.dbl-harness-old-[0-9]+$")


def is_temp_name(name: str) -> bool:
    """Names of the temporaries that :mod:`harness.runtime.cache` creates, and no others.

    Those are ``.<name>.dbl-harness-<8 random>.tmp`` (``tempfile``'s random part) and
    ``.<name>.dbl-harness-old-<pid>``: a user's ``.draft.tmp`` never matches.
    """
    return bool(_TEMP.match(name))


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
                if not (Path(dirpath) / name).is_symlink():
                    shutil.rmtree(Path(dirpath) / name, ignore_errors=True)
                dirnames.remove(name)
                removed += 1
        for name in filenames:
            if is_temp_name(name):
                with contextlib.suppress(FileNotFoundError):
                    (Path(dirpath) / name).unlink()
                removed += 1
    return removed


def _lock_holder(text: bytes) -> str:
    """Who holds a run lock, in words, from the pid its holder wrote into the lock file."""
    word = text.decode(errors="replace").strip()
    if not word.isdigit():  # between the holder's flock and its write of its pid
        return "another harness run (starting up: its pid is not written yet)"
    pid = int(word)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return f"a process started by harness run pid {pid} (which has exited)"
    except PermissionError:  # alive, another user's
        pass
    return f"another harness run (pid {pid})"


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
            raise HarnessError(
                f"{directory}: {_lock_holder(os.pread(fd, 64, 0))} is writing into this "
                "directory; wait for it to finish, or choose another --out"
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
        # The pid stays in the file: the flock, not the file's text, says whether a run holds it,
        # and a process a run started (a pool worker) may hold the lock after the run has exited.
        os.close(fd)  # releases the flock (unless a child inherited it)

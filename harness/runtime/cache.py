"""Atomic outputs and content-keyed stage caches.

Every stage writes into a temporary sibling and renames it into place, so a crash leaves either
the previous result or the new one, never a half-written file. A stage directory is complete
when its ``manifest.json`` exists; the manifest is written last.

An entry's key hashes its stage's parts (``harness/<stage>/keys.py``) with the code's fingerprint:
the keys of the entries it reads and the config it uses, never the options that only change how
a stage runs (workers, shards, batches, the device): changing those reuses every entry.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import inspect
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from harness import __version__
from harness.errors import CacheError
from harness.runtime.outdirs import TEMP_TAG

log = logging.getLogger(__name__)

_UMASK = os.umask(0)
os.umask(_UMASK)


#: Modules that no cached stage runs, as paths under ``harness/`` (a folder: all of it): the
#: reports, figures and the report page are rebuilt on every run, and the command layer only reads
#: arguments into the config (whose values are in the keys). Editing them never recomputes a
#: stage; editing any other module recomputes every stage.
NOT_IN_STAGES = frozenset(
    {
        "cli",  # the package: argument parsing, handlers and the console view
        "reports/write.py",
        "reports/render.py",
        "reports/tables.py",
        "reports/leaderboard.py",
        "reports/plots.py",
        "reports/html",
        "evaluate/aps.py",
        "evaluate/chance.py",
        "ingest/inspect.py",
        "ingest/folder_inspect.py",
        "runtime/gc.py",
    }
)
#: The package's own folder (this module is ``harness/runtime/cache.py``).
PACKAGE_DIR = Path(__file__).resolve().parents[1]


def code_fingerprint(package_dir: Path | None = None) -> str:
    """The package version plus a hash of the source of every module a cached stage can run.

    It is part of every stage key, so an upgrade (or any edit of such code) never reuses a cache
    entry that older code computed: correctness first, at the price of recomputing after a code
    change. Modules in :data:`NOT_IN_STAGES` are left out.
    """
    root = Path(package_dir) if package_dir is not None else PACKAGE_DIR
    h = hashlib.sha256(__version__.encode())
    for f in sorted(root.rglob("*.py")):
        rel = f.relative_to(root).as_posix()
        if any(rel == x or rel.startswith(x + "/") for x in NOT_IN_STAGES):
            continue
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return f"{__version__}+{h.hexdigest()[:12]}"


#: Computed once per process; stage keys include it.
CODE_FINGERPRINT = code_fingerprint()


def _apply_umask(path: Path, is_dir: bool) -> None:
    """mkstemp/mkdtemp create 0600/0700 entries; give outputs the modes the umask asks for."""
    os.chmod(path, (0o777 if is_dir else 0o666) & ~_UMASK)


def _jsonable(obj: Any) -> Any:
    if is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


#: A cache key's parts: what a stage's output depends on (``harness/<stage>/keys.py``).
Parts = tuple[Any, ...]


def without_empty(opts: dict[str, Any], name: str) -> dict[str, Any]:
    """``opts`` without ``name`` when it is empty (a key from before the field keeps its value)."""
    return {k: v for k, v in opts.items() if k != name or v}


def stable_hash(*parts: Any, length: int = 16) -> str:
    """A short sha256 of JSON-serialisable parts (dataclasses, dicts, paths, scalars)."""
    text = json.dumps([_jsonable(p) for p in parts], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def source_fingerprints(
    registry: Mapping[str, Callable[..., Any]], names: Iterable[str]
) -> dict[str, str]:
    """Source hashes of the functions of ``registry`` named in ``names`` from outside the package.

    Code inside the package is covered by :data:`CODE_FINGERPRINT`; a function a user registers
    (a proposal method, a fusion method) is not, so its own source goes into the stage's key.
    """
    out = {}
    for name in names:
        fn = registry.get(name)
        if fn is None or getattr(fn, "__module__", "").startswith("harness."):
            continue
        try:
            src = inspect.getsource(fn)
        except (OSError, TypeError):
            src = getattr(fn, "__qualname__", repr(fn))
        out[name] = hashlib.sha256(src.encode()).hexdigest()[:16]
    return out


def content_sha(path: Path, full: bool = False) -> str:
    """SHA-256 of a file's content (1 MiB blocks): 16 hex digits, or all 64 with ``full``."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest() if full else h.hexdigest()[:16]


def _summed(rel: str) -> bool:
    """Files of a cache entry whose checksum the manifest records: all but an image store's."""
    return not rel.startswith("images/")


def relative_to_root(path: Path | str, root: Path | None) -> str:
    """``{data_root}/...`` for a path under ``root``, else the absolute path (for cache keys).

    Keys name inputs by their place in the data root, so a moved data root keeps its keys.
    """
    p = Path(path).resolve()
    if root is not None and p.is_relative_to(Path(root).resolve()):
        return "{data_root}/" + p.relative_to(Path(root).resolve()).as_posix()
    return str(p)


def file_fingerprint(path: Path, root: Path | None = None) -> dict[str, Any]:
    """Cheap identity of a file or directory tree: relative names, sizes and mtimes.

    The path itself enters relative to ``root`` (the data root) where it lies under it.
    """
    path = Path(path)
    name = relative_to_root(path, root)
    if path.is_file():
        st = path.stat()
        return {"path": name, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    entries = []
    for p in sorted(path.rglob("*")):
        if p.is_file():
            st = p.stat()
            entries.append((str(p.relative_to(path)), st.st_size, st.st_mtime_ns))
    return {"path": name, "digest": stable_hash(entries)}


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``.

    Rename it onto ``path`` only if the block succeeds.
    """
    path = Path(path).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{TEMP_TAG}-", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        _apply_umask(tmp_path, is_dir=False)
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


@contextlib.contextmanager
def atomic_dir(path: Path) -> Iterator[Path]:
    """Yield a temporary directory.

    On success it replaces ``path`` (an older ``path`` is kept on failure).
    """
    path = Path(path).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{TEMP_TAG}-", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        _apply_umask(tmp, is_dir=True)
        if path.exists():
            old = path.with_name(f".{path.name}.{TEMP_TAG}-old-{os.getpid()}")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_json(path: Path, obj: Any) -> None:
    """Write JSON atomically, keys sorted, so equal content gives equal bytes."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_jsonable(obj), indent=2, sort_keys=True, default=str) + "\n")


def write_parquet(path: Path, df: pd.DataFrame | pa.Table, schema: pa.Schema | None = None) -> None:
    """Write a parquet table atomically (no pandas index, deterministic bytes for equal data)."""
    table = (
        df
        if isinstance(df, pa.Table)
        else pa.Table.from_pandas(df, schema=schema, preserve_index=False)
    )
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd")


def read_cached_parquet(path: Path, columns: list[str] | None = None) -> pd.DataFrame:
    """Read a parquet file of a cache entry.

    A damaged file is a :class:`CacheError` naming the entry.
    """
    try:
        return pd.read_parquet(path, columns=columns)
    except (OSError, ValueError, pa.ArrowException) as err:
        entry = Path(path).parent
        raise CacheError(
            f"{path}: damaged cache file ({type(err).__name__}: {err}); remove {entry} and "
            "rerun to rebuild it"
        ) from None


def write_text(path: Path, text: str) -> None:
    """Write a text file atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


class StageCache:
    """A directory of completed stage outputs, one subdirectory per (stage, key).

    ``run(name, key_parts, build)`` returns the stage directory, calling ``build(tmp_dir)`` only
    when no complete directory for that key exists. ``build`` fills ``tmp_dir`` and may return a
    dict stored in the manifest (counts, timings).
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def key(self, name: str, *key_parts: Any) -> str:
        """The entry key of stage ``name``: a hash of its parts and the code fingerprint."""
        return stable_hash(name, CODE_FINGERPRINT, *key_parts)

    def path(self, name: str, key: str) -> Path:
        """The directory of entry ``key`` of stage ``name``."""
        return self.root / name / key

    def is_done(self, name: str, key: str) -> bool:
        """A complete entry: its manifest reads and every file it lists has the recorded size.

        A damaged entry (a truncated file, a manifest cut short) is removed, so it is rebuilt.
        """
        path = self.path(name, key)
        if not (path / "manifest.json").exists():
            return False
        problem = self._damage(path)
        if problem is None:
            return True
        log.warning("%s: cache entry %s is damaged (%s); rebuilding it", name, path, problem)
        shutil.rmtree(path, ignore_errors=True)
        return False

    @staticmethod
    def _damage(path: Path) -> str | None:
        """Why the entry at ``path`` is not whole (None: it is).

        Every file's size, and every checksum the manifest records, is verified: a flipped byte
        is damage as a cut file is. Images of an ingest entry's image store carry no checksum
        (there can be hundreds of thousands; a damaged one fails when it is decoded).
        """
        try:
            man = json.loads((path / "manifest.json").read_text())
        except (OSError, ValueError) as err:
            return f"manifest.json unreadable: {err}"
        if not isinstance(man, dict):
            return "manifest.json is not an object"
        sums = man.get("sha256") or {}
        for rel, size in (man.get("files") or {}).items():
            f = path / rel
            try:
                actual = f.stat().st_size
            except OSError:
                return f"{rel} is missing"
            if actual != size:
                return f"{rel} has {actual} bytes, {size} expected"
            want = sums.get(rel)
            if want is not None and content_sha(f, full=True) != want:
                return f"{rel} does not match its checksum (its bytes changed)"
        return None

    def manifest(self, name: str, key: str) -> dict[str, Any]:
        """The manifest of a complete entry.

        Raises:
            CacheError: The manifest is unreadable (the message says which entry to remove).
        """
        path = self.path(name, key) / "manifest.json"
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise CacheError(
                f"{path}: unreadable cache manifest ({err}); remove {path.parent} and rerun"
            ) from None

    def run(
        self,
        name: str,
        key_parts: tuple[Any, ...],
        build: Callable[[Path], dict[str, Any] | None],
    ) -> tuple[Path, bool]:
        """Return (stage dir, ran) where ``ran`` says whether ``build`` was called."""
        key = self.key(name, *key_parts)
        final = self.path(name, key)
        if self.is_done(name, key):
            log.info("%s: cached (%s), skipping", name, final)
            return final, False
        with atomic_dir(final) as tmp:
            t0 = time.perf_counter()
            info = build(tmp) or {}
            build_s = time.perf_counter() - t0
            files = {
                str(p.relative_to(tmp)): p.stat().st_size
                for p in sorted(tmp.rglob("*"))
                if p.is_file()
            }
            sums = {rel: content_sha(tmp / rel, full=True) for rel in files if _summed(rel)}
            write_json(
                tmp / "manifest.json",
                {
                    "stage": name,
                    "key": key,
                    "info": info,
                    "files": files,
                    "sha256": sums,
                    # what building it took here (Table L's cost columns); never part of a key
                    "build_s": round(build_s, 4),
                },
            )
        log.info("%s: wrote %s", name, final)
        return final, True


def open_memmap_reserved(path: Path, dtype: Any, shape: tuple[int, ...]) -> np.memmap:
    """A new ``.npy`` memmap whose disk blocks are reserved up front.

    Writing into a sparse memmap on a full disk kills the process with SIGBUS ("Bus error") and
    no message; reserving the blocks turns that into an ``OSError(ENOSPC)`` here, which the CLI
    reports as one line.
    """
    arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.dtype(dtype), shape=shape)
    fd = os.open(path, os.O_RDWR)
    try:
        os.posix_fallocate(fd, 0, os.fstat(fd).st_size)
    except OSError as err:
        if err.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            del arr
            raise
    finally:
        os.close(fd)
    return arr

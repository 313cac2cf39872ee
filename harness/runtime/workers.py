"""Worker processes for library calls that hold process-wide state: one job at a time each.

OpenCV's Selective Search orders its regions with the C library's ``rand()``, the process's one
generator: threads would share it, so frames run side by side in processes instead, each seeded
before every frame. A worker is ``python -m harness.runtime.workers`` (nothing of the caller's
script is imported again, whatever guards it has), fed pickled ``(function, args)`` jobs on its
standard input; it answers each with a pickled ``(ok, result)`` on its standard output. The
functions are module-level ones of the package, found by name.
"""

from __future__ import annotations

import atexit
import importlib
import os
import pickle
import queue
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any, BinaryIO

from harness.errors import HarnessError


class _Worker:
    """One worker process and its pipes."""

    def __init__(self, preload: tuple[str, ...] = ()) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "harness.runtime.workers", *preload],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=os.environ.copy(),  # the parent's kernel pins with it
        )

    def call(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> Any:
        """``fn(*args)`` in this worker, its exception raised here."""
        stdin, stdout = self.proc.stdin, self.proc.stdout
        if stdin is None or stdout is None:  # pragma: no cover - Popen made both pipes
            raise HarnessError("a worker process has no pipes")
        try:
            pickle.dump((fn.__module__, fn.__qualname__, args), stdin, protocol=5)
            stdin.flush()
            ok, got = pickle.load(stdout)
        except (BrokenPipeError, EOFError, pickle.UnpicklingError) as err:
            raise HarnessError(
                f"a worker process ({fn.__qualname__}) ended with exit code "
                f"{self.proc.poll()}: {type(err).__name__}"
            ) from None
        if not ok:  # the worker's exception, raised here as the call would have raised it
            raise (
                got
                if isinstance(got, BaseException)
                else HarnessError(f"a worker process ({fn.__qualname__}) failed: {got}")
            )
        return got

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:  # pragma: no cover - a stuck worker
            self.proc.kill()


class Workers:
    """``n`` worker processes, started on first use; :meth:`call` blocks a thread for one.

    As a context manager the workers end with it. Each thread that calls takes a free worker, so
    ``n`` threads keep ``n`` processes busy.
    """

    def __init__(self, n: int, preload: tuple[str, ...] = ()) -> None:
        self.n = max(1, n)
        self.preload = preload  # modules each worker imports as it starts, before its first job
        self._free: queue.Queue[_Worker] = queue.Queue()
        self._all: list[_Worker] = []
        self._lock = threading.Lock()

    def start(self) -> Workers:
        """Start every worker now (each imports :attr:`preload` while the caller goes on)."""
        with self._lock:
            while len(self._all) < self.n:
                w = _Worker(self.preload)
                self._all.append(w)
                self._free.put(w)
        return self

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` in a worker process (``fn``: a module-level function of the package)."""
        with self._lock:
            if self._free.empty() and len(self._all) < self.n:
                w = _Worker(self.preload)
                self._all.append(w)
                self._free.put(w)
        w = self._free.get()
        try:
            return w.call(fn, args)
        finally:
            self._free.put(w)

    def close(self) -> None:
        """End every worker (each finishes the job it holds first)."""
        for w in self._all:
            w.close()
        self._all.clear()

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_SHARED: dict[tuple[int, tuple[str, ...]], Workers] = {}
_SHARED_LOCK = threading.Lock()


def shared_workers(n: int, preload: tuple[str, ...] = ()) -> Workers:
    """This process's pool of ``n`` workers (started now), kept for every later stage that asks.

    A run's stages (the map's proposals, then the new session's) reuse one pool rather than
    start processes for each; the pool ends when this process exits.
    """
    key = (max(1, n), tuple(preload))
    with _SHARED_LOCK:
        if key not in _SHARED:
            _SHARED[key] = Workers(*key).start()
        return _SHARED[key]


@atexit.register
def _close_shared() -> None:
    for w in _SHARED.values():
        w.close()
    _SHARED.clear()


def _serve(inp: BinaryIO, out: BinaryIO) -> None:
    """Answer jobs until the input ends."""
    while True:
        try:
            module, name, args = pickle.load(inp)
        except EOFError:
            return
        try:
            fn: Any = importlib.import_module(module)
            for part in name.split("."):
                fn = getattr(fn, part)
            reply: tuple[bool, Any] = (True, fn(*args))
        except Exception as err:
            reply = (False, err)
        try:
            data = pickle.dumps(reply, protocol=5)
        except Exception:
            data = pickle.dumps((False, f"{type(reply[1]).__name__}: {reply[1]}"), protocol=5)
        out.write(data)
        out.flush()


if __name__ == "__main__":
    # the answers go on the real standard output; anything a library prints goes to stderr
    _out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    for _module in sys.argv[1:]:  # preloaded: imported while the caller prepares the first job
        importlib.import_module(_module)
    _serve(sys.stdin.buffer, _out)

"""Progress of long work: tqdm bars on a terminal, log lines elsewhere.

On a terminal, a bar refreshed at most once a second. Where stderr is not a terminal (a log file,
CI, ``nohup``), the bar would be silent, so the same work logs one INFO line at most every
:data:`LOG_EVERY_S` seconds instead (``proposals grid5: 40/120 batch (33%, 2.1 batch/s)``): long
work shows progress wherever its output goes, and short work logs nothing.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

from tqdm import tqdm

T = TypeVar("T")

log = logging.getLogger(__name__)

#: Seconds between two progress log lines where there is no terminal for a bar.
LOG_EVERY_S = 10.0


def _terminal() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


class LogProgress:
    """A progress count that logs itself every ``every`` seconds (the first after ``every``)."""

    def __init__(
        self,
        desc: str,
        unit: str,
        total: int | None,
        every: float = LOG_EVERY_S,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.desc, self.unit, self.total, self.every = desc, unit, total, every
        self.clock = clock or time.monotonic
        self.n = 0
        self.start = self.last = self.clock()

    def update(self, k: int = 1) -> None:
        """Count ``k`` more units; log where ``every`` seconds passed since the last line."""
        self.n += k
        now = self.clock()
        if now - self.last < self.every:
            return
        self.last = now
        rate = self.n / max(now - self.start, 1e-9)
        done = f"{self.n}/{self.total}" if self.total else f"{self.n}"
        share = f"{100 * self.n / self.total:.0f}%, " if self.total else ""
        log.info("%s: %s %s (%s%.3g %s/s)", self.desc, done, self.unit, share, rate, self.unit)

    def close(self) -> None:
        """Nothing to clear (the bar's counterpart)."""


def _logged(iterable: Iterable[T], bar: LogProgress) -> Iterator[T]:
    for item in iterable:
        yield item
        bar.update(1)


def progress(iterable: Iterable[T], desc: str, unit: str = "it") -> Iterable[T]:
    """Wrap ``iterable`` in a progress bar named ``desc`` counting ``unit``.

    A tqdm bar refreshed at most once a second on a terminal, else log lines (:class:`LogProgress`).

    Args:
        iterable: The work items.
        desc: What the bar says it is doing.
        unit: The name of one item.

    Returns:
        An iterable over the same items.
    """
    if not _terminal():
        total = len(iterable) if hasattr(iterable, "__len__") else None  # type: ignore[arg-type]
        return _logged(iterable, LogProgress(desc, unit, total))
    return tqdm(
        iterable,
        desc=desc,
        unit=unit,
        mininterval=1.0,
        dynamic_ncols=True,
        leave=False,
        disable=None,
    )


def progress_bar(total: int, desc: str, unit: str = "it") -> Any:
    """A bar to ``update(k)`` by hand (a training loop's steps); log lines off a terminal."""
    if not _terminal():
        return LogProgress(desc, unit, total)
    return tqdm(total=total, desc=desc, unit=unit, mininterval=1.0, leave=False, disable=None)

"""A reader thread that runs an iterator ahead of its consumer.

Decoding and cropping frames (OpenCV, libjpeg) and encoding crops (torch) both release the GIL, so
a thread that decodes the next batches while the current one is encoded makes a stage cost about
the larger of the two rather than their sum. Items come out in the producer's order, so results
are the same with or without the thread.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import TypeVar

from harness.errors import HarnessError

T = TypeVar("T")

_DONE = object()


def prefetched(items: Iterable[T], depth: int) -> Iterator[T]:
    """The items of ``items``, produced up to ``depth`` ahead by a reader thread.

    ``depth`` 0: no thread, ``items`` as they are. An exception in the producer is raised here,
    at the item where it happened. Closing the returned generator early (``break``, an error in
    the consumer) stops the thread after the item it is producing.
    """
    if depth <= 0:
        yield from items
        return
    box: queue.Queue[tuple[bool, object]] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(entry: tuple[bool, object]) -> bool:
        while not stop.is_set():
            try:
                box.put(entry, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for x in items:
                if not put((True, x)):
                    return
            put((True, _DONE))
        except BaseException as err:  # handed to the consumer, raised there
            put((False, err))

    reader = threading.Thread(target=produce, name="prefetch", daemon=True)
    reader.start()
    try:
        while True:
            ok, x = box.get()
            if not ok:
                if not isinstance(x, BaseException):  # the producer sends (False, its error)
                    raise HarnessError(f"prefetch: the producer stopped with {x!r}, not an error")
                raise x
            if x is _DONE:
                return
            yield x  # type: ignore[misc]
    finally:
        stop.set()
        reader.join()

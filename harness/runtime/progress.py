"""Progress bars for long work (tqdm; silent when stderr is not a terminal)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")


def progress(iterable: Iterable[T], desc: str, unit: str = "it") -> Iterable[T]:
    """Wrap ``iterable`` in a progress bar named ``desc`` counting ``unit``.

    Refreshed at most once a second.

    Args:
        iterable: The work items.
        desc: What the bar says it is doing.
        unit: The name of one item.

    Returns:
        An iterable over the same items.
    """
    return tqdm(
        iterable,
        desc=desc,
        unit=unit,
        mininterval=1.0,
        dynamic_ncols=True,
        leave=False,
        disable=None,
    )

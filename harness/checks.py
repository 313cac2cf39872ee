"""The range checks every config section uses, all at load time, before any work.

Each failure is one ConfigError naming the key, its value and what is allowed.
"""

from __future__ import annotations

import math
from typing import Any

from harness.errors import ConfigError


def check_value(ok: bool, where: str, key: str, value: Any, allowed: str) -> None:
    """Unless ``ok``, one ConfigError naming ``where``, ``key``, its value and what is allowed."""
    if not ok:
        raise ConfigError(f"{where}: {key} = {value!r} is out of range; allowed: {allowed}")


def check_range(
    where: str, key: str, pair: tuple[float, float], lo: float = 0.0, hi: float = 1.0
) -> None:
    """Unless ``lo <= low <= high <= hi``, one ConfigError naming the pair."""
    check_value(
        lo <= pair[0] <= pair[1] <= hi,
        where,
        key,
        list(pair),
        f"[low, high] with {lo} <= low <= high <= {hi}",
    )


#: The largest seed accepted anywhere (numpy's and torch's generators take 64-bit seeds).
MAX_SEED = 2**63 - 1


def is_finite(v: Any) -> bool:
    """Whether ``v`` is a finite int or float."""
    return isinstance(v, int | float) and math.isfinite(v)


def check_device(device: str, where: str, key: str) -> None:
    """A CUDA device asked for by name must exist on this machine (``auto`` falls back)."""
    if not device.startswith("cuda"):
        return
    import torch

    if not torch.cuda.is_available():
        raise ConfigError(
            f"{where}: {key} = {device!r}, but torch sees no CUDA device on this machine; use "
            "'auto' (CUDA where there is one, else the CPU) or 'cpu'"
        )

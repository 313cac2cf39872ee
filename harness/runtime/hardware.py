"""What the machine's processors can do (native bf16 products), and what ``precision`` means."""

from __future__ import annotations

from harness.kernels import cpu_flags

#: CPU flags of a native bf16 matrix product (AVX512-BF16 dot products, AMX tiles).
CPU_BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def has_bf16(device: str) -> bool:
    """Whether ``device`` (``cpu`` or ``cuda``) multiplies bf16 matrices natively."""
    if device == "cuda":
        import torch

        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    return any(f in cpu_flags() for f in CPU_BF16_FLAGS)


def resolve_precision(precision: str, device: str) -> str:
    """``fp32`` or ``bf16``, what ``precision`` means (``device`` is kept for the callers).

    ``auto`` is fp32 on every device (docs/decisions.md, *One answer on every CPU*): a table must
    not depend on whether the machine multiplies bf16 natively, so bf16 is used only where asked for
    by name (``python -m bench --only precision`` measures what it costs and gains).
    """
    del device
    return "fp32" if precision == "auto" else precision


def rank_precision(precision: str) -> str:
    """The exact ranking engine's candidate product for ``[descriptor] precision``.

    ``bf16`` only where asked for by name: ``auto`` (and ``fp32``) rank in fp32. The bf16
    product's error bound leaves frames undecided, each measured exactly at 37 to 59 times the
    cost of its fp32 comparison (``python -m bench --only ranking``), so bf16 ranks faster only
    where few frames are undecided (under 1.3 to 2.0% with a 4x bf16 product; the fixture leaves
    5.6%), which depends on the localizer, not the machine (``docs/decisions.md``, *bf16 candidate
    product*).
    """
    return "bf16" if precision == "bf16" else "fp32"

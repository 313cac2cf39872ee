"""One answer on every CPU of the kind: the numeric libraries' kernels pinned to AVX2.

torch (ATen's vectorised ops, oneDNN's convolutions), MKL, OpenBLAS, numpy's SIMD loops, OpenCV
and faiss each pick their kernels by the CPU they find. On an AVX-512 machine they take other
code paths than on an AVX2-only one, whose last bits differ (SVML's ``arctan2``, a convolution's
summation order); the fixture's autoencoder then trains to other weights from the same seed and
every table downstream moves in the second decimal. So, before any of them is imported, the
harness caps each at the level every machine of the kind has: AVX2 with FMA.

The caps are environment variables read once, when each library loads (or, for ATen, at its
first dispatch); :func:`pin` sets those not already set (a value the user set wins) and is called
by ``harness/__init__.py``, so ``import harness`` before numpy or torch is enough, and every
``harness`` command is pinned. ``HARNESS_KERNELS=native`` leaves every library to its own choice
(faster on AVX-512, tables of that machine only). :func:`report` says what took effect, for
``run.json``.

Measured (``docs/decisions.md``, *One answer on every CPU*): on an AVX2-only EPYC the caps change
no byte; on an AVX-512 + bf16 EPYC, fp32 training under ATen's and oneDNN's caps gives the AVX2
machine's model bit for bit (31 s against 26 s uncapped on the fixture).
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

#: The switch: ``avx2`` (the default) caps the kernels, ``native`` leaves them alone.
ENV = "HARNESS_KERNELS"
LEVELS = ("avx2", "native")

#: The caps every x86-64 machine with AVX2 gets (each library's own variable; see the docstring).
AVX2_CAPS = {
    "ATEN_CPU_CAPABILITY": "avx2",  # torch's vectorised ops (BatchNorm, sigmoid, Adam, ...)
    "ONEDNN_MAX_CPU_ISA": "AVX2",  # torch's convolutions (oneDNN): no AVX-512, no AMX
    "DNNL_MAX_CPU_ISA": "AVX2",  # the same, oneDNN's older name
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",  # MKL (torch's BLAS) takes AVX-512 paths on Intel CPUs
    "OPENBLAS_CORETYPE": "Haswell",  # numpy's and scipy's BLAS and LAPACK (eigh of the PCA)
    "FAISS_OPT_LEVEL": "avx2",  # faiss built per level
    "FAISS_SIMD_LEVEL": "AVX2",  # faiss with dynamic dispatch (faiss-cpu 1.12 and later)
}
#: Caps set only where the CPU has AVX-512 (elsewhere OpenCV prints a line for an unknown feature).
AVX512_CAPS = {
    # numpy 2's dispatch groups, and numpy 1's names of the same (an unknown name is ignored)
    "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512_SKX AVX512_CLX "
    "AVX512_CNL",
    # OpenCV's own dispatch, by the names cv2.getCPUFeaturesLine() prints (hyphenated: the
    # underscored AVX512_SKX of before was an unknown name, so that cap was never in force)
    "OPENCV_CPU_DISABLE": "AVX512-SKX",
    # Intel IPP inside OpenCV picks its kernels by the CPU on its own (k0, AVX-512, on an AVX-512
    # EPYC); "avx2" gives it the l9 kernels an AVX2-only machine runs
    "OPENCV_IPP": "avx2",
}
#: Libraries that read their caps when loaded: imported before :func:`pin`, they are not capped.
EARLY = ("numpy", "torch", "cv2", "faiss", "scipy")


def cpu_flags() -> frozenset[str]:
    """The first processor's flags from ``/proc/cpuinfo`` (empty where there is none)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return frozenset()
    line = next((x for x in text.splitlines() if x.partition(":")[0].strip() == "flags"), "")
    return frozenset(line.partition(":")[2].split())


def level() -> str:
    """The level asked for: ``$HARNESS_KERNELS`` or ``avx2``; an unknown value is an error."""
    v = os.environ.get(ENV, "avx2").strip().lower() or "avx2"
    if v not in LEVELS:
        raise ValueError(f"{ENV}={v!r}: expected one of {', '.join(LEVELS)}")
    return v


def caps(flags: frozenset[str] | None = None, asked: str | None = None) -> dict[str, str]:
    """The environment variables :func:`pin` sets on a CPU with ``flags``.

    None off x86-64, or without AVX2 and FMA (nothing above the level to cap), or where
    ``native`` is asked for.
    """
    flags = cpu_flags() if flags is None else flags
    asked = level() if asked is None else asked
    if asked == "native" or platform.machine().lower() not in ("x86_64", "amd64"):
        return {}
    if not {"avx2", "fma"} <= flags:
        return {}
    out = dict(AVX2_CAPS)
    if any(f.startswith("avx512") for f in flags) or "amx_bf16" in flags:
        out.update(AVX512_CAPS)
    return out


def pin() -> list[str]:
    """Set each cap not already in the environment; returns the libraries loaded too early.

    A library in :data:`EARLY` that was imported before this call kept its own kernels: the
    caller (``harness/__init__.py``) leaves it to :func:`report` to say so.
    """
    try:
        want = caps()
    except ValueError:  # an unknown $HARNESS_KERNELS: the command line says so (cli.main)
        return []
    for k, v in want.items():
        os.environ.setdefault(k, v)
    return [m for m in EARLY if m in sys.modules] if want else []


#: What :func:`pin` found already imported when the package was first imported.
LOADED_BEFORE: list[str] = []


def report() -> dict[str, object]:
    """The kernels in force, for ``run.json`` and ``detect.json``.

    The level asked, the caps set, torch's capability and the libraries that were loaded before
    the caps could apply.
    """
    out: dict[str, object] = {
        "asked": level(),
        "caps": {k: os.environ[k] for k in caps() if k in os.environ},
        "loaded_before_pin": list(LOADED_BEFORE),
    }
    if "torch" in sys.modules:
        out["torch_cpu_capability"] = str(sys.modules["torch"].backends.cpu.get_cpu_capability())
    return out

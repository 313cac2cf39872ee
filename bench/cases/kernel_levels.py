"""The full-NCLT projection under ``HARNESS_KERNELS=native``: the rated stages' kernels timed in
two fresh processes, one per kernel level, and the avx2 projection rescaled by what they measure.

The harness caps every numeric library at AVX2 by default (``harness/kernels.py``), so a table is
the same on every CPU of the kind; ``native`` lets each library take its widest kernels (and
``[descriptor] precision = "bf16"`` multiplies in bf16 where the CPU does so natively), with tables
of that machine only. Running the whole NCLT-scale workload twice would double the case, so the
kernels that bound the rated stages are timed under each level in the same run, and the stages'
projected minutes are rescaled by the ratio.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from typing import Any

import numpy as np

from harness.kernels import cpu_flags

from .common import ROOT, bf16_native, emit, kernel_env, matmul_gflops


def kernel_job() -> None:
    """In this process, at the level it was started with: the fp32 product rate, the encoder's
    ms a 256 x 256 subimage (folded, ``encode_batch`` automatic) and the training step's ms a
    subimage at batch 16, in bf16 where ``native`` meets a CPU that multiplies it natively."""
    import torch
    from torch import nn

    import harness.kernels
    from harness.descriptors import AutoencoderDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder, autocast, to_tensor
    from harness.descriptors.config import DescriptorConfig

    bf16 = harness.kernels.level() == "native" and bf16_native()
    rng = np.random.default_rng(0)
    crops = rng.integers(0, 256, (64, 256, 256, 3), dtype=np.uint8)
    cfg = DescriptorConfig(
        input_size=256, device="cpu", input_norm="per_crop", precision="bf16" if bf16 else "fp32"
    )
    d = AutoencoderDescriptor(cfg)
    torch.manual_seed(0)
    d.model = ConvAutoencoder().eval()
    d.encode(crops[:8])
    enc = []
    for _ in range(3):
        t0 = time.perf_counter()
        d.encode(crops)
        enc.append((time.perf_counter() - t0) / len(crops) * 1000)
    model = ConvAutoencoder().to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    step = []
    for i in range(5):  # the first step warms the kernels up: not counted
        t0 = time.perf_counter()
        x = to_tensor(crops[16 * (i % 4) : 16 * (i % 4 + 1)], torch.device("cpu"), True)
        with autocast(torch.device("cpu"), bf16):
            loss = nn.functional.mse_loss(model(x).float(), x)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step.append((time.perf_counter() - t0) / 16 * 1000)
    print(
        json.dumps(
            {
                "level": harness.kernels.level(),
                "bf16": bf16,
                "fp32_gflops": matmul_gflops(),
                "encoder_ms": statistics.median(enc),
                "train_ms": statistics.median(step[1:]),
                "kernels": harness.kernels.report(),
            }
        ),
        flush=True,
    )


def _job(level: str) -> dict[str, Any]:
    """:func:`kernel_job` in a fresh process started with ``HARNESS_KERNELS=level``, without the
    caps this process inherited (:func:`kernel_env`)."""
    proc = subprocess.run(
        [sys.executable, "-m", "bench.cases", "kerneljob"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
        env=kernel_env(level),
    )
    if proc.returncode != 0:
        raise SystemExit(f"kernel job at {level} failed:\n{proc.stderr[-3000:]}")
    got = dict(json.loads(proc.stdout.strip().splitlines()[-1]))
    torch_level = str(got["kernels"].get("torch_cpu_capability", ""))
    if level == "native" and torch_level == "AVX2" and "avx512f" in cpu_flags():
        raise SystemExit("the kernel job at native ran torch at AVX2 on an AVX-512 CPU: a cap")
    return got


def _best(jobs: list[dict[str, Any]]) -> dict[str, Any]:
    """The fastest of each figure over ``jobs`` (noise only ever slows a kernel down)."""
    best = dict(jobs[0])
    for k in ("encoder_ms", "train_ms"):
        best[k] = min(j[k] for j in jobs)
    best["fp32_gflops"] = max(j["fp32_gflops"] for j in jobs)
    return best


def native_projection(stages: dict[str, float], encoder_subimages: float) -> None:
    """Emit the kernels under each level and the rated stages' minutes under ``native``.

    Args:
        stages: Projected seconds of the rated stages at avx2: ``proposals``, ``training``,
            ``descriptors`` and ``ranking``.
        encoder_subimages: Subimages the whole NCLT encodes (the descriptors stage).
    """
    runs: dict[str, list[dict[str, Any]]] = {"avx2": [], "native": []}
    for _ in range(2):  # interleaved, the best of two each: the machine's drift hits both levels
        for level in runs:
            runs[level].append(_job(level))
    avx2, native = (_best(runs[level]) for level in ("avx2", "native"))
    for key, what, unit in (
        ("encoder_ms", "encoder 256x256, folded", "ms/subimage"),
        ("train_ms", "training step 256x256, batch 16", "ms/subimage"),
        ("fp32_gflops", "fp32 product", "GFLOP/s"),
    ):
        emit(
            f"full-nclt kernels at native: {what}",
            [native[key]],
            unit,
            at_avx2=round(avx2[key], 3),
            native_vs_avx2=round(native[key] / avx2[key], 3),
            notes=f"HARNESS_KERNELS=native {native[key]:.2f} against the default avx2 caps "
            f"{avx2[key]:.2f}, each the best of two fresh processes, interleaved, in this run"
            + ("; bf16 (native on this CPU)" if native["bf16"] else "; fp32: no native bf16 here"),
        )
    enc_delta = (native["encoder_ms"] - avx2["encoder_ms"]) / 1000 * encoder_subimages
    train = stages["training"] * native["train_ms"] / avx2["train_ms"]
    ranking = stages["ranking"] * avx2["fp32_gflops"] / native["fp32_gflops"]
    at_native = {
        "proposals": stages["proposals"],
        "training": train,
        "descriptors": max(stages["descriptors"] + enc_delta, 0.0),
        "ranking": ranking,
    }
    total, base = sum(at_native.values()), sum(stages.values())
    emit(
        "full-nclt projection: the rated stages at HARNESS_KERNELS=native",
        [total / 60],
        "min (CPU)",
        at_avx2_min=round(base / 60, 1),
        native_vs_avx2=round(total / base, 3),
        notes="projected, not run: the avx2 stages rescaled by their kernels measured at both "
        "levels in this run (the descriptors' encoder time, the training step, the ranking's "
        "fp32 product); proposals (OpenCV) as at avx2; "
        + ", ".join(f"{k} {v / 60:.1f} min" for k, v in at_native.items())
        + "; tables at native are this machine's only (docs/decisions.md, One answer on every CPU)",
    )

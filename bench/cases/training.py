"""Bench case ``training``: the autoencoder's training step and held-out evaluation against the
fp32 product rate, at the full-NCLT input size (256 x 256)."""

from __future__ import annotations

import statistics
import time

import numpy as np

from .common import autoencoder_flops, emit, matmul_gflops


def case_training(quick: bool) -> None:
    """One training step (forward, backward, Adam) at batch 16 and 64, and the held-out loss
    (forward only), each in subimages per second, against the fp32 product rate measured here.

    The full-NCLT projection rates training at its FLOPs at the product rate; these rows say how
    far the step's own convolutions are from that rate, and what one held-out evaluation costs.
    """
    import torch
    from torch import nn

    from harness.descriptors.autoencoder import ConvAutoencoder, held_out_loss, to_tensor

    peak = matmul_gflops()
    train_f = autoencoder_flops(train=True)
    cpu = torch.device("cpu")
    rng = np.random.default_rng(0)
    steps = 3 if quick else 6
    for batch in (16, 64):
        torch.manual_seed(0)
        model = ConvAutoencoder().to(memory_format=torch.channels_last)
        model.train()
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        data = rng.integers(0, 256, (batch, 256, 256, 3), dtype=np.uint8)
        secs = []
        for _ in range(steps + 1):  # the first step warms oneDNN's kernels up: not counted
            t0 = time.perf_counter()
            x = to_tensor(data, cpu, True)
            loss = nn.functional.mse_loss(model(x).float(), x)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            secs.append(time.perf_counter() - t0)
        rate = [batch / s for s in secs[1:]]
        gf = statistics.median(rate) * train_f / 1e9
        emit(
            f"autoencoder training step 256x256, batch {batch}",
            rate,
            "subimages/s",
            gflops=round(gf, 1),
            fraction_of_peak=round(gf / peak, 3),
            notes=f"forward + backward + Adam, per_crop input; {train_f / 1e9:.2f} GFLOP a "
            f"subimage; {gf:.1f} GFLOP/s = {gf / peak:.0%} of the fp32 product rate "
            f"{peak:.0f} GFLOP/s; {1000 / statistics.median(rate):.1f} ms a subimage",
        )
    n = 64 if quick else 160
    data = rng.integers(0, 256, (n, 256, 256, 3), dtype=np.uint8)
    hold = np.arange(n)
    held_out_loss(model, data, hold[:16], 16, cpu, True)
    runs = []
    for _ in range(2 if quick else 3):
        t0 = time.perf_counter()
        held_out_loss(model, data, hold, 16, cpu, True)
        runs.append(n / (time.perf_counter() - t0))
    ms = 1000 / statistics.median(runs)
    emit(
        "autoencoder held-out loss 256x256 (forward only)",
        runs,
        "subimages/s",
        notes=f"{ms:.1f} ms a held-out crop; the full-NCLT settings (8,000 training crops, "
        f"holdout 0.1, eval_every 50 over 375 steps) measure 800 crops 8 times: "
        f"{800 * 8 * ms / 1000:.0f} s a training",
    )

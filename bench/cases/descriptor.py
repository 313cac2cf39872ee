"""Bench case ``descriptor``."""

from __future__ import annotations

import json
import statistics

import numpy as np

from .common import emit, matmul_gflops, peak_rss_mib, timed


def case_descriptor(quick: bool) -> None:
    """Autoencoder encoding throughput and its fraction of the measured matmul FLOP rate."""
    import torch

    from harness.config.schema import DescriptorConfig
    from harness.descriptors import AutoencoderDescriptor, HogDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder, to_tensor

    peak = matmul_gflops()
    print(
        json.dumps(
            {
                "case": "matmul fp32 peak (best of 512..2048 square)",
                "median": peak,
                "unit": "GFLOP/s",
                "runs": [peak],
                "peak_rss_mib": peak_rss_mib(),
                "notes": f"torch threads {torch.get_num_threads()}",
            }
        ),
        flush=True,
    )
    for size, batch in ((256, 32), (64, 128)):
        cfg = DescriptorConfig(input_size=size, batch_size=batch, device="cpu")
        d = AutoencoderDescriptor(cfg)
        d.model = ConvAutoencoder().eval()
        n = batch * (2 if quick else 4)
        x = np.random.default_rng(0).integers(0, 256, (n, size, size, 3), dtype=np.uint8)
        d.encode(x[:batch])
        runs = timed(lambda d=d, x=x: d.encode(x), repeat=3)
        c1, c2, c3 = 32, 32, 16
        flops = 2 * 9 * (size**2 * 3 * c1 + (size // 2) ** 2 * c1 * c2 + (size // 4) ** 2 * c2 * c3)
        rate = [n / t for t in runs]
        gf = statistics.median(rate) * flops / 1e9
        emit(
            f"autoencoder encode {size}x{size}",
            rate,
            "subimages/s",
            gflops=round(gf, 1),
            fraction_of_peak=round(gf / peak, 3),
            notes=f"folded encoder, {d.encode_batch} subimages per call; {flops / 1e6:.0f} "
            f"MFLOP/subimage; {gf:.1f} GFLOP/s = {gf / peak:.0%} of matmul peak; "
            f"{1000 / statistics.median(rate):.2f} ms/subimage",
        )
        if (
            size == 256
            # the plain trained model in batches of 32 (the path before the folded encoder)
        ):
            model, per_crop = d.model, False

            def plain(x=x, model=model, batch=batch, per_crop=per_crop) -> None:
                with torch.inference_mode():
                    for i in range(0, len(x), batch):
                        model.encode(to_tensor(x[i : i + batch], torch.device("cpu"), per_crop))

            plain()
            base = [n / t for t in timed(plain, repeat=3)]
            emit(
                "autoencoder encode 256x256, plain model batch 32",
                base,
                "subimages/s",
                notes=f"{statistics.median(base) * flops / 1e9 / peak:.0%} of matmul peak; folded "
                f"encoder speed-up {statistics.median(rate) / statistics.median(base):.1f}x",
            )
    h = HogDescriptor(DescriptorConfig())
    x = np.random.default_rng(0).integers(0, 256, (256, 64, 64, 3), dtype=np.uint8)
    emit("hog encode 64x64", [256 / t for t in timed(lambda: h.encode(x))], "subimages/s")

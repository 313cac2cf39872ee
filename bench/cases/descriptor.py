"""Bench case ``descriptor``."""

from __future__ import annotations

import dataclasses
import json
import statistics

import numpy as np

from .common import bf16_native, bf16_words, emit, matmul_gflops, peak_rss_mib, timed


def case_descriptor(quick: bool) -> None:
    """Autoencoder encoding throughput and its fraction of the measured matmul FLOP rate."""
    import torch

    from harness.descriptors import AutoencoderDescriptor, HogDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder, to_tensor
    from harness.descriptors.config import DescriptorConfig

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
    _bf16(peak, quick)
    h = HogDescriptor(DescriptorConfig())
    x = np.random.default_rng(0).integers(0, 256, (256, 64, 64, 3), dtype=np.uint8)
    emit("hog encode 64x64", [256 / t for t in timed(lambda: h.encode(x))], "subimages/s")


def _bf16(peak: float, quick: bool) -> None:
    """The bf16 product rate (the encoder's limit under ``precision = "bf16"``) beside fp32's, and
    the encoder at 256x256 in bf16: native only where the CPU has AVX512-BF16 or AMX and no cap
    holds the kernels at AVX2 (``HARNESS_KERNELS=native``; :func:`bf16_native`)."""
    import torch

    from harness.descriptors import AutoencoderDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder
    from harness.descriptors.config import DescriptorConfig

    native = bf16_native()
    n = 1024 if quick else 2048
    a, b = torch.randn(n, n).bfloat16(), torch.randn(n, n).bfloat16()
    a @ b
    gf = [2 * n**3 / t / 1e9 for t in timed(lambda: a @ b, repeat=3)]
    emit(
        f"matmul bf16 {n}x{n}",
        gf,
        "GFLOP/s",
        native_bf16=native,
        notes=f"{statistics.median(gf) / peak:.2f}x the fp32 peak measured above; native bf16 "
        f"product in this run: {bf16_words(native)}",
    )
    cfg = DescriptorConfig(input_size=256, batch_size=32, device="cpu")
    rates = {}
    for precision in ("fp32", "bf16"):
        d = AutoencoderDescriptor(dataclasses.replace(cfg, precision=precision))
        d.model = ConvAutoencoder().eval()
        x = np.random.default_rng(0).integers(0, 256, (32, 256, 256, 3), dtype=np.uint8)
        d.encode(x[:4])
        rates[precision] = [len(x) / t for t in timed(lambda d=d, x=x: d.encode(x), repeat=3)]
    ratio = statistics.median(rates["bf16"]) / statistics.median(rates["fp32"])
    emit(
        "autoencoder encode 256x256, precision bf16",
        rates["bf16"],
        "subimages/s",
        native_bf16=native,
        vs_fp32=round(ratio, 2),
        notes=f"{ratio:.2f}x the fp32 encoder in the same run; native bf16: {bf16_words(native)}",
    )

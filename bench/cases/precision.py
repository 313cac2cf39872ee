"""Bench case ``precision``: what bf16 costs in R@1 on the NCLT-scale workload.

``harness reproduce`` of ``bench/nclt_scale.toml`` (125 frames per session, 1,232 x 1,616 JPEG
frames, the paper's 256 x 256 autoencoder) twice, each in its own process and directory with
nothing cached: ``[descriptor] precision = "fp32"``, then ``"bf16"`` (the encoder trained and run
in bfloat16, ranking's candidates from a bfloat16 product). One row per run with its R@1 and
Table I / Table S figures, then their differences (the goal: none beyond 0.01).

Both runs take the same kernel level, so their difference is the precision's alone: where the CPU
has bf16 instructions (AVX512-BF16 or AMX), ``HARNESS_KERNELS=native`` (under the default AVX2
caps a bf16 product is emulated even there), and the bf16 run's wall time is then a figure of
bf16 speed; elsewhere the default caps, and the bf16 run is emulated: its figures say what bf16
costs in accuracy, its wall time nothing about speed. Each row names the level.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

from .common import (
    DATA,
    ROOT,
    bf16_words,
    emit,
    kernel_env,
    nclt_scale_workload,
    reproduce_subprocess,
)
from .fixture_figures import measured_share, run_tables

PRECISIONS = ("fp32", "bf16")


def _config(precision: str, where: Path) -> Path:
    """``bench/nclt_scale.toml`` with ``[descriptor] precision`` set, written into ``where``."""
    text = (ROOT / "bench" / "nclt_scale.toml").read_text()
    if "\n[descriptor]\n" not in text:
        raise SystemExit("bench/nclt_scale.toml has no [descriptor] table")
    text = text.replace("\n[descriptor]\n", f'\n[descriptor]\nprecision = "{precision}"\n', 1)
    path = where / f"nclt_scale_{precision}.toml"
    path.write_text(text.replace('data_root = "bench/', f'data_root = "{ROOT}/bench/'))
    return path


def _figures(out: Path, run: dict[str, Any]) -> dict[str, float]:
    """R@1 over every query subimage, Table I at RoC-max 0.05 and Table S's rank fusion AP."""
    row, t1, _, ts = run_tables(out)
    rf = ts.loc["rank_fusion"]
    return {
        "recall_at_1": float(row["recall_at_1"]),
        "median_r": float(row["median_r"]),
        "t1_rank_fusion_005": float(t1.loc["rank_fusion", "0.05"]),
        "t1_rank_no_fusion_005": float(t1.loc["rank_no_fusion", "0.05"]),
        "ts_rank_fusion_005": float(rf["ap"]),
        # method §9: every AP with its interval, its measured floor and chance band
        "ts_rank_fusion_ci_low_005": float(rf["ci_low"]),
        "ts_rank_fusion_ci_high_005": float(rf["ci_high"]),
        "ts_floor_005": float(rf["floor"]),
        "ts_chance_high_005": float(rf["chance_high"]),
        "subimages": int(row["subimages"]),
        **measured_share(run["counts"].get("rank_counts", {})),
    }


def case_precision(quick: bool) -> None:
    from harness.runtime.hardware import has_bf16

    n = 24 if quick else 125
    root = nclt_scale_workload(n)
    native = has_bf16("cpu")
    level = "native" if native else "avx2"
    got: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(dir=DATA, prefix="precision-") as tmp:
        for precision in PRECISIONS:
            out, run, usage, wall = reproduce_subprocess(
                _config(precision, Path(tmp)), root, f"precision-{precision}-", kernel_env(level)
            )
            asked = run.get("kernels", {}).get("asked")
            if asked != level:
                raise SystemExit(f"the {precision} run took kernels {asked!r}, not {level!r}")
            got[precision] = fig = _figures(out, run)
            shutil.rmtree(out)
            emit(
                f"precision [{precision}] NCLT-scale R@1 [{n} frames/session]",
                [fig["recall_at_1"]],
                "R@1",
                figures=fig,
                wall_s=round(wall, 1),
                train_s=round(float(run["timings_s"].get("model", 0.0)), 1),
                native_bf16=native,
                kernels=level,
                peak_rss_mib=usage.ru_maxrss / 1024,
                notes=f"bench/nclt_scale.toml with [descriptor] precision = {precision!r}, "
                f"HARNESS_KERNELS={level}; nothing cached"
                + ("" if precision == "fp32" else f"; bf16 native: {bf16_words(native)}"),
            )
    diff = {
        k: round(got["bf16"][k] - got["fp32"][k], 4)
        for k in (
            "recall_at_1",
            "t1_rank_fusion_005",
            "t1_rank_no_fusion_005",
            "ts_rank_fusion_005",
        )
    }
    worst = max(abs(v) for v in diff.values())
    verdict = "met" if worst <= 0.01 else "NOT met"
    emit(
        f"precision bf16 minus fp32, NCLT-scale [{n} frames/session]",
        [diff["recall_at_1"]],
        "R@1",
        vs_fp32=diff,
        kernels=level,
        notes=f"both at HARNESS_KERNELS={level}; bf16 minus fp32: "
        + ", ".join(f"{k} {v:+.4f}" for k, v in diff.items())
        + f"; largest {worst:.4f} (goal: none beyond 0.01: {verdict}); Table S rank fusion "
        + "; ".join(
            f"{p} {got[p]['ts_rank_fusion_005']:.3f} [{got[p]['ts_rank_fusion_ci_low_005']:.3f}, "
            f"{got[p]['ts_rank_fusion_ci_high_005']:.3f}] (floor {got[p]['ts_floor_005']:.3f}, "
            f"chance band up to {got[p]['ts_chance_high_005']:.3f})"
            for p in PRECISIONS
        ),
    )

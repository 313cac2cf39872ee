"""What every bench case shares: paths, timing, the JSON line each result prints, workloads."""

from __future__ import annotations

import json
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


DATA = ROOT / "bench" / ".data"


def bf16_native() -> bool:
    """Whether this process multiplies bf16 natively: the CPU has AVX512-BF16 or AMX, and no cap
    holds torch's kernels at AVX2.

    Every bench process imports ``harness``, which pins the libraries at AVX2 as every ``harness``
    command does (``harness/kernels.py``); under those caps a bf16 product is emulated even on a
    CPU that has the instructions, so the CPU's flags alone would call an emulated figure native.
    """
    from harness.kernels import AVX2_CAPS
    from harness.runtime.hardware import has_bf16

    # the caps a bf16 product and convolution go through: oneDNN's and MKL's
    gates = ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "MKL_ENABLE_INSTRUCTIONS")
    capped = any(os.environ.get(k) == AVX2_CAPS[k] for k in gates)
    return has_bf16("cpu") and not capped


def bf16_words(native: bool) -> str:
    """Whether a bf16 figure of this process is one of bf16 speed, in words."""
    from harness.runtime.hardware import has_bf16

    if native:
        return "yes"
    if has_bf16("cpu"):
        return "no: emulated under the default AVX2 caps (not a figure of bf16 speed)"
    return "no: this CPU has none (emulated: not a figure of bf16 speed)"


def kernel_env(level: str) -> dict[str, str]:
    """The environment for a child process started at ``HARNESS_KERNELS=level``.

    This process's environment without the caps its own ``import harness`` set: inherited, they
    would hold a ``native`` child at AVX2 (its bf16 then emulated: 0.09x the rate of its fp32
    encoder on an AMX Xeon, case ``descriptor``). A cap set to another value than the pinned one
    is the user's and is kept.
    """
    from harness.kernels import AVX2_CAPS, AVX512_CAPS, ENV

    pinned = {**AVX2_CAPS, **AVX512_CAPS}
    env = {k: v for k, v in os.environ.items() if pinned.get(k) != v and k != ENV}
    return {**env, ENV: level}


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def emit(case: str, runs: list[float], unit: str, **extra: object) -> None:
    print(
        json.dumps(
            {
                "case": case,
                "median": statistics.median(runs),
                "unit": unit,
                "runs": runs,
                "peak_rss_mib": peak_rss_mib(),
                **extra,
            }
        ),
        flush=True,
    )


def rated(
    case: str, ms: float, limit: float, notes: str, digits: int = 2, unit: str = "ms/frame"
) -> None:
    """One row of a time beside its limit: ``limit_ms`` and ``vs_limit`` (None: no limit)."""
    emit(
        case,
        [ms],
        unit,
        limit_ms=round(limit, digits),
        vs_limit=round(ms / limit, 2) if limit > 0 else None,
        notes=notes,
    )


def timed(fn, repeat: int = 3) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def size_of(path: Path) -> int:
    return (
        path.stat().st_size
        if path.is_file()
        else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    )


def read_all(path: Path) -> None:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    for f in files:
        with open(f, "rb") as fh:
            while fh.read(1 << 22):
                pass


def matmul_gflops() -> float:
    import torch

    best = 0.0
    for n in (512, 1024, 2048):  # the best square float32 matmul rate: the machine's measured peak
        a, b = torch.randn(n, n), torch.randn(n, n)
        a @ b
        best = max(best, 2 * n**3 / min(timed(lambda a=a, b=b: a @ b, repeat=5)) / 1e9)
    return best


def fit_exponent(x: list[float], y: list[float]) -> float:
    """Least-squares slope of log y against log x: cost ~ x ** exponent."""
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def random_db(m: int, dim: int, rng: np.random.Generator, tag: str = "") -> Path:
    path = DATA / f"db-{m}-{dim}{tag}.npy"
    if not path.exists():
        DATA.mkdir(parents=True, exist_ok=True)
        arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(m, dim))
        for s in range(0, m, 4096):
            blk = rng.standard_normal((min(4096, m - s), dim), dtype=np.float32)
            arr[s : s + len(blk)] = (blk / np.linalg.norm(blk, axis=1, keepdims=True)).astype(
                np.float16
            )
        arr.flush()
        del arr
    return path


STAGES = (
    "ingest",
    "pairs",
    "proposals",
    "model",
    "descriptor_shards",
    "ranks",
    "samples",
    "labels_ap_reports",
)


def nclt_scale_workload(frames: int) -> Path:
    """The synthetic NCLT-scale logs.

    Four ROS2 sqlite3 bags of 1,232 x 1,616 JPEG frames (generated once).
    """
    from harness.fixture import FixtureSpec, generate

    root = DATA / f"nclt-scale-{frames}"
    if not (root / "fixture.json").exists():
        spec = FixtureSpec(
            frames=frames, width=1232, height=1616, render_scale=4, loop_scale=3.0, objects=6
        )
        generate(root, spec, formats=("ros2",) * len(spec.sessions))
    return root


def reproduce_subprocess(
    config: Path, root: Path, prefix: str, env: dict[str, str] | None = None
) -> tuple[Path, dict[str, Any], Any, float]:
    """``harness reproduce`` of ``config`` on ``root`` in its own process, into a new directory,
    with ``env`` (this process's environment where None; :func:`kernel_env` for another level).

    Returns:
        (run directory, its run.json, ``os.wait4`` resource usage (peak RSS of the run and the
        loader workers it waited for), wall seconds).
    """
    import subprocess
    import sys

    out = Path(tempfile.mkdtemp(dir=DATA, prefix=prefix))
    cmd = [
        sys.executable,
        "-m",
        "harness.cli",
        "reproduce",
        "--config",
        str(config),
        "--data-root",
        str(root),
        "--out",
        str(out),
    ]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**(os.environ if env is None else env), "TQDM_DISABLE": "1"},
    )
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"reproduce {config.name} on {root} failed:\n{err[-3000:]}")
    return out, json.loads((out / "run.json").read_text()), usage, wall


def anon_peak_poller() -> tuple[Any, dict[str, float]]:
    """A thread sampling this process's anonymous resident memory (RssAnon) every 20 ms.

    Peak RSS (VmHWM) also counts the database's file pages mapped by the memmap, which the
    kernel may drop at will; RssAnon is what the process itself holds.
    """
    import threading

    peak = {"anon_mib": 0.0}
    stop = threading.Event()

    def poll() -> None:
        while not stop.is_set():
            for line in Path("/proc/self/status").read_text().splitlines():
                if line.startswith("RssAnon:"):
                    peak["anon_mib"] = max(peak["anon_mib"], int(line.split()[1]) / 1024)
            stop.wait(0.02)

    th = threading.Thread(target=poll, daemon=True)
    th.start()
    return stop, peak


def autoencoder_flops(size: int = 256, train: bool = False) -> float:
    """FLOPs of the paper's autoencoder on one ``size`` x ``size`` subimage, counted by torch.

    ``train``: a training step's (forward and backward of encoder and decoder); else the
    encoder's forward, what encoding a subimage costs.
    """
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from harness.descriptors.autoencoder import ConvAutoencoder

    model = ConvAutoencoder()
    x = torch.randn(1, 3, size, size)
    with FlopCounterMode(display=False) as counter:
        if train:
            model(x).square().mean().backward()
        else:
            with torch.no_grad():
                model.encode(x)
    return float(counter.get_total_flops())


def kernel_limits(out: Path, fp32_before: float = 0.0) -> dict[str, float]:
    """The kernels' rates measured now, the limits a stage is rated against.

    ``fp32_before``: the fp32 rate measured before the run; the faster of the two is the
    machine's (a shared machine's product rate was measured at 90 and 178 GFLOP/s in two runs of
    one hour, and a limit from the slower reading makes the stages look at their kernels).

    JPEG decode ms per frame (32 of the run's ingested JPEG frames, libjpeg-turbo through
    ``cv2.imread``: full size and at 1/2; ``decode_pixels`` their size), the product rate the
    encoder can reach (bf16 where the CPU multiplies it natively, else fp32; GFLOP/s), the fp32
    rate and the memory bandwidth (GB/s, a 256 MiB copy: read + write), and ``cores``, the
    cores this process may run on: a decode runs on one core, so a stage that decodes a frame on
    each core at once is bounded by ``decode_ms / cores`` a frame, as the products' rates are
    already the cores' together.
    """
    import cv2
    import torch

    store = out / "cache" / "ingest"  # the ingested frames, not the report's own images
    jpegs = sorted(p for p in store.rglob("*") if p.suffix.lower() in (".jpg", ".jpeg"))[-32:]
    if not jpegs:
        raise SystemExit(f"no stored JPEG frame in {store}: the decode limit cannot be measured")
    shape = cv2.imread(str(jpegs[0]), cv2.IMREAD_COLOR).shape

    def decode(flag: int) -> float:
        for p in jpegs[:4]:
            cv2.imread(str(p), flag)  # the page cache and the library warm
        return 1000 * statistics.median(
            min(timed(lambda p=p: cv2.imread(str(p), flag), repeat=3)) for p in jpegs
        )

    fp32 = max(matmul_gflops(), fp32_before)
    native = bf16_native()
    rate = fp32
    if native:
        a, b = torch.randn(2048, 2048).bfloat16(), torch.randn(2048, 2048).bfloat16()
        rate = max(rate, 2 * 2048**3 / min(timed(lambda: a @ b, repeat=5)) / 1e9)
    src = np.ones(2**28 // 8)
    dst = np.empty_like(src)
    copy = min(timed(lambda: np.copyto(dst, src), repeat=5))
    return {
        "decode_ms": decode(cv2.IMREAD_COLOR),
        "decode_pixels": float(shape[0] * shape[1]),
        "decode_half_ms": decode(cv2.IMREAD_REDUCED_COLOR_2),
        "product_gflops": rate,
        "fp32_gflops": fp32,
        "native_bf16": float(native),
        "bandwidth_gbs": 2 * src.nbytes / copy / 1e9,
        "cores": float(len(os.sched_getaffinity(0))),
    }


def product_note(lim: dict[str, float]) -> str:
    """Which product rate a limit used, in words."""
    if lim["native_bf16"]:
        return f"{lim['product_gflops']:.0f} GFLOP/s (bf16, native)"
    return f"{lim['product_gflops']:.0f} GFLOP/s (fp32; bf16 native: {bf16_words(False)})"


def pair_tables(rows: list[tuple], pairs: list[tuple], props: list[tuple]) -> tuple[Any, Any, Any]:
    """The frame, pair and proposal tables of a generated set of pairs (the local and keypoints
    cases): ``rows`` (session, camera, utime, image, width, height), ``pairs`` (query key, map key,
    season pair), ``props`` (frame key, method, box id, x1, y1, x2, y2)."""
    import pandas as pd

    frames = pd.DataFrame(rows, columns=["session", "camera", "utime", "image", "width", "height"])
    pair_df = pd.DataFrame(pairs, columns=["q_session", "q_camera", "q_utime", "r_session",
                                           "r_camera", "r_utime", "season_pair"])  # fmt: skip
    prop_df = pd.DataFrame(props, columns=["session", "camera", "utime", "proposal_method",
                                           "box_id", "x1", "y1", "x2", "y2"])  # fmt: skip
    return frames, pair_df, prop_df


def one_thread_descriptor_work(frames: list[tuple[str, np.ndarray]]) -> tuple[float, float]:
    """Seconds on one thread for ``frames`` (image path, its boxes (k, 4)): decoding each and
    cropping its boxes at 256 (``crop_pyramid``), then the autoencoder's inference encoder on the
    crops in batches of two (random weights: the same convolutions, the same time), with torch on
    one thread. Their sum divided by the cores is what lanes that waste nothing would take."""
    import torch

    from harness.descriptors.autoencoder import ConvAutoencoder, inference_encoder, to_tensor
    from harness.descriptors.crops import crop_pyramid
    from harness.descriptors.extract import torch_threads

    model = ConvAutoencoder((32, 32, 16)).eval()
    model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    enc, cpu = inference_encoder(model), torch.device("cpu")
    with torch_threads(1), torch.inference_mode():
        crops = [crop_pyramid(f, b, 256) for f, b in frames[:2]]  # warm
        t0 = time.perf_counter()
        crops = [crop_pyramid(f, b, 256) for f, b in frames]
        t1 = time.perf_counter()
        for c in crops:
            [enc(to_tensor(c[i : i + 2], cpu, True)).numpy() for i in range(0, len(c), 2)]
        t2 = time.perf_counter()
    return t1 - t0, t2 - t1

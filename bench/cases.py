"""Individual benchmark cases; each prints one JSON line per result (run by bench/__main__.py)."""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "bench" / ".data"


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def emit(case: str, runs: list[float], unit: str, **extra: object) -> None:
    print(json.dumps({"case": case, "median": statistics.median(runs), "unit": unit, "runs": runs, "peak_rss_mib": peak_rss_mib(), **extra}), flush=True)


def timed(fn, repeat: int = 3) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _read_all(path: Path) -> None:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    for f in files:
        with open(f, "rb") as fh:
            while fh.read(1 << 22):
                pass


def case_ingest(quick: bool) -> None:
    """Ingest MB/s of each format next to the raw read speed of the same bytes (warm page cache)."""
    from harness.config import IngestConfig, SessionConfig
    from harness.fixture import FixtureSpec, generate
    from harness.fixture.generate import FORMATS, session_path

    spec = FixtureSpec(frames=16 if quick else 48, width=480, height=640, objects=0, sessions=(("2012-01-22", "WI"),), changed_sessions=())
    root = DATA / f"ingest-{spec.frames}"
    if not (root / "fixture.json").exists():
        generate(root, spec, all_formats=True)
    from harness.ingest import ingest_session

    for fmt in FORMATS:
        src = root / session_path(fmt, "2012-01-22")
        nbytes = _size(src)
        _read_all(src)  # warm: the raw read below is from the page cache, an upper bound
        raw = timed(lambda s=src: _read_all(s))
        extra = {}
        if fmt != "nclt":
            from harness.ingest.logs import list_topics, stream

            kind = "mcap" if src.suffix == ".mcap" else ("ros1" if src.suffix == ".bag" else "ros2")
            topics = tuple(list_topics(src, kind))
            des = timed(lambda s=src, k=kind, t=topics: [None for _ in stream(s, k, t)])
            extra["deserialize_mb_s"] = round(statistics.median([nbytes / 1e6 / t for t in des]), 1)
        tmp = Path(tempfile.mkdtemp())
        ing = timed(lambda s=src, t=tmp: ingest_session(SessionConfig(name="2012-01-22", source=str(s)), IngestConfig(), t / "o"))
        shutil.rmtree(tmp)
        mb = nbytes / 1e6
        emit(f"ingest[{fmt}]", [mb / t for t in ing], "MB/s", raw_read_mb_s=round(statistics.median([mb / t for t in raw]), 1), **extra,
             notes=f"{mb:.1f} MB, {spec.frames} frames {spec.width}x{spec.height}; ratio to raw read {statistics.median([mb / t for t in ing]) / statistics.median([mb / t for t in raw]):.3f}")


def case_crops(quick: bool) -> None:
    """Crop + resize to 256x256 of 16 boxes from 1,232 x 1,616 JPEG frames (decode included)."""
    import cv2
    import pandas as pd

    from harness.crops import iter_crops

    n = 8 if quick else 32
    d = DATA / "crops"
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        p = d / f"{i}.jpg"
        if not p.exists():
            img = cv2.GaussianBlur(rng.integers(0, 256, (1616, 1232, 3), dtype=np.uint8), (0, 0), 3)
            cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        paths.append(str(p))
    rows = []
    for p in paths:
        for _k in range(16):
            x1, y1 = rng.uniform(0, 800), rng.uniform(0, 1100)
            rows.append((p, x1, y1, x1 + rng.uniform(100, 430), y1 + rng.uniform(100, 510)))
    df = pd.DataFrame(rows, columns=["image", "x1", "y1", "x2", "y2"])
    for workers in (0, 2):
        runs = timed(lambda w=workers: [None for _ in iter_crops(df, df["image"], 256, frames_per_batch=4, num_workers=w)], repeat=3)
        emit(f"crop+resize[workers={workers}]", [len(df) / t for t in runs], "subimages/s", notes=f"{n} JPEG frames 1232x1616, 16 boxes each")


def _matmul_gflops() -> float:
    import torch

    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    a @ b
    runs = timed(lambda: a @ b, repeat=5)
    return 2 * 2048**3 / min(runs) / 1e9


def case_descriptor(quick: bool) -> None:
    """Autoencoder encoding throughput and its fraction of the machine's measured matmul FLOP rate."""
    import torch

    from harness.config import DescriptorConfig
    from harness.descriptors import AutoencoderDescriptor, HogDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder

    peak = _matmul_gflops()
    print(json.dumps({"case": "matmul fp32 2048^3", "median": peak, "unit": "GFLOP/s", "runs": [peak], "peak_rss_mib": peak_rss_mib(), "notes": f"torch threads {torch.get_num_threads()}"}), flush=True)
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
        emit(f"autoencoder encode {size}x{size}", rate, "subimages/s",
             notes=f"{flops / 1e6:.0f} MFLOP/subimage; {statistics.median(rate) * flops / 1e9:.1f} GFLOP/s = {statistics.median(rate) * flops / 1e9 / peak:.0%} of matmul peak; {1000 / statistics.median(rate):.2f} ms/subimage")
    h = HogDescriptor(DescriptorConfig())
    x = np.random.default_rng(0).integers(0, 256, (256, 64, 64, 3), dtype=np.uint8)
    emit("hog encode 64x64", [256 / t for t in timed(lambda: h.encode(x))], "subimages/s")


def case_ranking(quick: bool) -> None:
    """Exact ranking throughput (query subimages/s) at database sizes 1k, 10k, 100k (D = 16,384, float16 memmap)."""
    from harness.retrieval import image_ranks, image_ranks_faiss

    peak = _matmul_gflops()
    dim = 16384
    sizes = (1000, 10_000) if quick else (1000, 10_000, 100_000)
    nq = 256
    rng = np.random.default_rng(0)
    q = rng.standard_normal((nq, dim), dtype=np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for m in sizes:
        path = DATA / f"db-{m}-{dim}.npy"
        if not path.exists():
            DATA.mkdir(parents=True, exist_ok=True)
            arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(m, dim))
            for s in range(0, m, 4096):
                blk = rng.standard_normal((min(4096, m - s), dim), dtype=np.float32)
                arr[s : s + len(blk)] = (blk / np.linalg.norm(blk, axis=1, keepdims=True)).astype(np.float16)
            arr.flush()
            del arr
        db = np.load(path, mmap_mode="r")
        frame = np.arange(m) // 16
        gt = rng.choice(np.unique(frame), nq)
        runs = timed(lambda db=db, frame=frame, gt=gt: image_ranks(q, db, frame, gt, chunk_rows=8192, query_batch=nq), repeat=3 if m < 100_000 else 1)
        flops = 2 * nq * m * dim
        rate = [nq / t for t in runs]
        emit(f"rank exact db={m}", rate, "query subimages/s",
             notes=f"{statistics.median([flops / t / 1e9 for t in runs]):.1f} GFLOP/s = {statistics.median([flops / t / 1e9 for t in runs]) / peak:.0%} of matmul peak ({peak:.0f} GFLOP/s)")
        if m <= 10_000:
            full = np.asarray(db, np.float32)
            base = timed(lambda full=full: ((q**2).sum(1)[:, None] + (full**2).sum(1)[None] - 2 * q @ full.T), repeat=3)
            emit(f"numpy baseline distance matrix db={m}", [nq / t for t in base], "query subimages/s", notes="np.matmul of the whole float32 database, no per-frame minimum")
            fr = timed(lambda full=full, frame=frame, gt=gt: image_ranks_faiss(q, full, frame, gt, k=256), repeat=3)
            emit(f"rank faiss flat k=256 db={m}", [nq / t for t in fr], "query subimages/s")


def case_fusion(quick: bool) -> None:
    """Fusion + labels + AP per query image (5 grid boxes + 12 random boxes per image)."""
    import pandas as pd

    from harness.config import SplitsConfig
    from harness.metrics import average_precision
    from harness.proposals import grid5
    from harness.runner import fuse_samples
    from harness.splits import label, paper_splits

    rng = np.random.default_rng(0)
    n_img = 50 if quick else 200
    rows, ann = [], []
    for i in range(n_img):
        boxes = [*grid5(1232, 1616).tolist()]
        for _ in range(12):
            x1, y1 = rng.uniform(0, 900), rng.uniform(0, 1200)
            boxes.append([x1, y1, x1 + rng.uniform(50, 330), y1 + rng.uniform(50, 410)])
        for k, b in enumerate(boxes):
            rows.append(("A", "c", i, "B", "c", i, "WI->SU", "grid5" if k < 5 else "yolo", k, *b, 1, 100, 1, rng.uniform(0.01, 1), rng.uniform(0, 2), True))
        ann.append(("A", "c", i, "change", 400.0, 500.0, 700.0, 900.0, "") if i % 2 else ("A", "c", i, "no-change", np.nan, np.nan, np.nan, np.nan, ""))
    ranks = pd.DataFrame(rows, columns=["q_session", "q_camera", "q_utime", "r_session", "r_camera", "r_utime", "season_pair", "method", "box_id", "x1", "y1", "x2", "y2", "rank", "L", "r_", "r", "d", "exact"])
    frames = pd.DataFrame({"session": "A", "camera": "c", "utime": np.arange(n_img), "width": 1232, "height": 1616})
    annotations = pd.DataFrame(ann, columns=["session", "camera", "utime", "status", "x1", "y1", "x2", "y2", "label"])

    def work() -> None:
        s, _ = fuse_samples(ranks, frames, annotations, 0, 4096)
        for sp in paper_splits(SplitsConfig()):
            lab = label(s["RoC"].to_numpy(), s["SoB"].to_numpy(), sp)
            for m in [c for c in s.columns if c.startswith("loc_")]:
                sel = (lab >= 0) & s[m].notna().to_numpy()
                average_precision(lab[sel] == 1, s[m].to_numpy()[sel])

    runs = timed(work, repeat=3)
    emit("fusion+labels+AP", [n_img / t for t in runs], "query images/s", notes="17 boxes per image, all proposal subsets, 5 splits x 6 methods")


def case_executor(quick: bool) -> None:
    """Descriptor + ranking stages of the fixture: local executor vs Ray with two local workers.

    The cache of a full local run is copied with its descriptor, ranking and fusion stages
    removed, and the run is timed from there (Ray's start-up not included).
    """
    import dataclasses

    from harness.config import load_config
    from harness.executors import LocalExecutor, RayExecutor
    from harness.fixture import FixtureSpec, generate
    from harness.runner import Pipeline

    world = DATA / "fixture"
    if not (world / "fixture.json").exists():
        generate(world, FixtureSpec())
    cfg = load_config(ROOT / "datasets" / "fixture.toml", data_root=str(world))
    cfg = dataclasses.replace(cfg, descriptor=dataclasses.replace(cfg.descriptor, shard_frames=16))
    base = DATA / "executor-base"
    if not (base / "table1.csv").exists():
        Pipeline(cfg, base).run()
    ray_ex = RayExecutor(num_cpus=2)
    results = {}
    for name, ex in (("local", LocalExecutor()), ("ray", ray_ex)):
        runs = []
        for _ in range(1 if quick else 3):
            tmp = Path(tempfile.mkdtemp(dir=DATA))
            shutil.copytree(base / "cache", tmp / "cache")
            for stage in ("descriptor_shards", "descriptors", "ranks", "samples"):
                shutil.rmtree(tmp / "cache" / stage, ignore_errors=True)
            t0 = time.perf_counter()
            Pipeline(cfg, tmp, executor=ex).run()
            runs.append(time.perf_counter() - t0)
            shutil.rmtree(tmp)
        results[name] = runs
        emit(f"descriptors+ranks+fusion [{name}]", runs, "s", notes="fixture: 256 frames, 16-frame shards")
    print(json.dumps({"case": "ray speed-up (local s / ray s)", "median": statistics.median(results["local"]) / statistics.median(results["ray"]), "unit": "x", "runs": [], "peak_rss_mib": peak_rss_mib(), "notes": "2 local workers on 2 cores"}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("case")
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    globals()[f"case_{a.case}"](a.quick)


if __name__ == "__main__":
    main()

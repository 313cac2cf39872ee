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
        ing = timed(lambda s=src, t=tmp: ingest_session(SessionConfig(name="2012-01-22", source=str(s)), IngestConfig(), t / "o", force=True))
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

    best = 0.0
    for n in (512, 1024, 2048):  # the best square float32 matmul rate: the machine's measured peak
        a, b = torch.randn(n, n), torch.randn(n, n)
        a @ b
        best = max(best, 2 * n**3 / min(timed(lambda a=a, b=b: a @ b, repeat=5)) / 1e9)
    return best


def case_descriptor(quick: bool) -> None:
    """Autoencoder encoding throughput and its fraction of the machine's measured matmul FLOP rate."""
    import torch

    from harness.config import DescriptorConfig
    from harness.descriptors import AutoencoderDescriptor, HogDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder, to_tensor

    peak = _matmul_gflops()
    print(json.dumps({"case": "matmul fp32 peak (best of 512..2048 square)", "median": peak, "unit": "GFLOP/s", "runs": [peak], "peak_rss_mib": peak_rss_mib(), "notes": f"torch threads {torch.get_num_threads()}"}), flush=True)
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
        emit(f"autoencoder encode {size}x{size}", rate, "subimages/s", gflops=round(gf, 1), fraction_of_peak=round(gf / peak, 3),
             notes=f"folded encoder, {d.encode_batch} subimages per call; {flops / 1e6:.0f} MFLOP/subimage; {gf:.1f} GFLOP/s = {gf / peak:.0%} of matmul peak; {1000 / statistics.median(rate):.2f} ms/subimage")
        if size == 256:  # the plain trained model in batches of 32 (the path before the folded encoder), same run
            model, per_crop = d.model, False

            def plain(x=x, model=model, batch=batch, per_crop=per_crop) -> None:
                with torch.inference_mode():
                    for i in range(0, len(x), batch):
                        model.encode(to_tensor(x[i : i + batch], torch.device("cpu"), per_crop))

            plain()
            base = [n / t for t in timed(plain, repeat=3)]
            emit("autoencoder encode 256x256, plain model batch 32", base, "subimages/s",
                 notes=f"{statistics.median(base) * flops / 1e9 / peak:.0%} of matmul peak; folded encoder speed-up {statistics.median(rate) / statistics.median(base):.1f}x")
    h = HogDescriptor(DescriptorConfig())
    x = np.random.default_rng(0).integers(0, 256, (256, 64, 64, 3), dtype=np.uint8)
    emit("hog encode 64x64", [256 / t for t in timed(lambda: h.encode(x))], "subimages/s")


def fit_exponent(x: list[float], y: list[float]) -> float:
    """Least-squares slope of log y against log x: cost ~ x ** exponent."""
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def _random_db(m: int, dim: int, rng: np.random.Generator) -> Path:
    path = DATA / f"db-{m}-{dim}.npy"
    if not path.exists():
        DATA.mkdir(parents=True, exist_ok=True)
        arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(m, dim))
        for s in range(0, m, 4096):
            blk = rng.standard_normal((min(4096, m - s), dim), dtype=np.float32)
            arr[s : s + len(blk)] = (blk / np.linalg.norm(blk, axis=1, keepdims=True)).astype(np.float16)
        arr.flush()
        del arr
    return path


def case_ranking(quick: bool) -> None:
    """Exact ranking throughput (query subimages/s) at database sizes 1k, 10k, 100k (D = 16,384, float16 memmap).

    2,048 query subimages per call (128 query frames x 16; a pipeline ranking unit holds up to
    512 frames x 16 = 8,192), query_batch 1,024 as configured by default. Each call streams the
    database once, so the float16 read and conversion are shared by all its queries; with only
    256 queries that share dominates at 100k (the extra row shows it).
    """
    from harness.retrieval import image_ranks, image_ranks_faiss

    peak = _matmul_gflops()
    dim = 16384
    sizes = (1000, 10_000) if quick else (1000, 10_000, 100_000)
    nq = 2048
    rng = np.random.default_rng(0)
    q = rng.standard_normal((nq, dim), dtype=np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    per_query_s = []
    for m in sizes:
        db = np.load(_random_db(m, dim, rng), mmap_mode="r")
        frame = np.arange(m) // 16
        gt = rng.choice(np.unique(frame), nq)
        runs = timed(lambda db=db, frame=frame, gt=gt: image_ranks(q, db, frame, gt, chunk_rows=8192, query_batch=1024), repeat=3 if m < 100_000 else 1)
        flops = 2 * nq * m * dim
        rate = [nq / t for t in runs]
        per_query_s.append(statistics.median(runs) / nq)
        gf = statistics.median([flops / t / 1e9 for t in runs])
        emit(f"rank exact db={m}", rate, "query subimages/s", gflops=round(gf, 1), fraction_of_peak=round(gf / peak, 3),
             notes=f"{nq} queries; {gf:.1f} GFLOP/s = {gf / peak:.0%} of matmul peak ({peak:.0f} GFLOP/s)")
        if m == max(sizes):
            small = timed(lambda db=db, frame=frame, gt=gt: image_ranks(q[:256], db, frame, gt[:256], chunk_rows=8192, query_batch=256), repeat=1)
            gf = 2 * 256 * m * dim / small[0] / 1e9
            emit(f"rank exact db={m}, 256 queries", [256 / t for t in small], "query subimages/s",
                 notes=f"{gf:.1f} GFLOP/s = {gf / peak:.0%} of peak: one database pass (read + float16 conversion) shared by only 256 queries")
        if m <= 10_000:
            full = np.asarray(db, np.float32)
            base = timed(lambda full=full: ((q**2).sum(1)[:, None] + (full**2).sum(1)[None] - 2 * q @ full.T), repeat=3)
            emit(f"numpy baseline distance matrix db={m}", [nq / t for t in base], "query subimages/s", notes="np.matmul of the whole float32 database, no per-frame minimum")
            fr = timed(lambda full=full, frame=frame, gt=gt: image_ranks_faiss(q, full, frame, gt, k=256), repeat=1)
            emit(f"rank faiss flat k=256 db={m}", [nq / t for t in fr], "query subimages/s")
    print(json.dumps({"case": "scaling: ranking time per query vs database size", "median": fit_exponent(list(sizes), per_query_s), "unit": "exponent",
                      "runs": [], "peak_rss_mib": peak_rss_mib(), "points": {"x": list(sizes), "y": per_query_s, "xlabel": "database subimages",
                                                                           "ylabel": "s per query subimage"}}), flush=True)


def case_fusion(quick: bool) -> None:
    """Fusion, then labels + AP, then pixel + image AP, per query image (5 grid boxes + 12 random
    boxes per image, every method of SPEC section 7), all measured in the same run."""
    import dataclasses

    import pandas as pd

    from harness.config import SplitsConfig, load_config
    from harness.fusion import fuse_samples
    from harness.metrics import average_precision
    from harness.proposals import grid5
    from harness.reports import _groups, _pixel_image_rows
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
            rank = int(rng.integers(1, 101))
            rows.append(("A", "c", i, "B", "c", i, "WI->SU", "grid5" if k < 5 else "yolo", k, *b, rank, 100, rank / 100, rng.uniform(0, 2), True))
        ann.append(("A", "c", i, "change", 400.0, 500.0, 700.0, 900.0, "") if i % 2 else ("A", "c", i, "no-change", np.nan, np.nan, np.nan, np.nan, ""))
    ranks = pd.DataFrame(rows, columns=["q_session", "q_camera", "q_utime", "r_session", "r_camera", "r_utime", "season_pair", "method", "box_id", "x1", "y1", "x2", "y2", "rank", "L", "r", "d", "exact"])
    frames = pd.DataFrame({"session": "A", "camera": "c", "utime": np.arange(n_img), "width": 1232, "height": 1616})
    annotations = pd.DataFrame(ann, columns=["session", "camera", "utime", "status", "x1", "y1", "x2", "y2", "label"])
    samples, _ = fuse_samples(ranks, frames, annotations, 0, 4096)
    allp = samples[samples["proposals"] == "all"].reset_index(drop=True)
    methods = tuple(c[4:] for c in samples.columns if c.startswith("loc_"))
    cfg = load_config(ROOT / "datasets" / "fixture.toml")
    cfg = dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, bootstrap=0))
    ids = {g: i for i, g in enumerate(sorted(set(_groups(allp))))}

    def fusion() -> None:
        fuse_samples(ranks, frames, annotations, 0, 4096)

    def labels_ap() -> None:
        for sp in paper_splits(SplitsConfig()):
            lab = label(allp["RoC"].to_numpy(), allp["SoB"].to_numpy(), sp)
            for m in methods:
                sel = (lab >= 0) & allp[f"loc_{m}"].notna().to_numpy()
                average_precision(lab[sel] == 1, allp[f"loc_{m}"].to_numpy()[sel])

    def pixel_image_ap() -> None:
        _pixel_image_rows(cfg, allp, frames, annotations, methods, ids)

    note = f"17 boxes per image, {len(methods)} methods"
    emit("fusion (all proposal subsets)", [n_img / t for t in timed(fusion, repeat=3)], "query images/s", notes=note)
    la = timed(labels_ap, repeat=3)
    emit("labels + AP (5 splits, Table I)", [1000 * t / n_img for t in la], "ms per query image", notes=note)
    px = timed(pixel_image_ap, repeat=3)
    emit("pixel AP + image AP (exact regions, Table P)", [1000 * t / n_img for t in px], "ms per query image",
         ratio_to_labels_ap=round(float(np.median(px) / np.median(la)), 2), notes=note + ", without bootstrap")


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


STAGES = ("ingest", "pairs", "proposals", "train", "descriptor_shards", "ranks", "fusion", "labels_ap_reports")


def nclt_scale_workload(frames: int) -> Path:
    """The synthetic NCLT-scale logs: four ROS2 sqlite3 bags of 1,232 x 1,616 JPEG frames (generated once)."""
    from harness.fixture import FixtureSpec, generate

    root = DATA / f"nclt-scale-{frames}"
    if not (root / "fixture.json").exists():
        spec = FixtureSpec(frames=frames, width=1232, height=1616, render_scale=4, loop_scale=3.0, objects=6)
        generate(root, spec, formats=("ros2",) * len(spec.sessions))
    return root


def case_e2e(quick: bool) -> None:
    """End-to-end Table I (``harness reproduce``, nothing cached) on the NCLT-scale workload, at
    several frame counts per session; per-stage times and their growth with the frame count.

    Each run is its own process; its peak RSS comes from ``os.wait4`` (that process and the
    data-loader workers it waited for).
    """
    import os
    import subprocess
    import sys

    counts = (24, 48) if quick else (125, 250, 500)
    stage_t: dict[str, list[float]] = {s: [] for s in STAGES}
    totals = []
    for n in counts:
        root = nclt_scale_workload(n)
        out = Path(tempfile.mkdtemp(dir=DATA, prefix="e2e-"))
        cmd = [sys.executable, "-m", "harness.cli", "reproduce", "--config", str(ROOT / "bench" / "nclt_scale.toml"), "--data-root", str(root), "--out", str(out)]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env={**os.environ, "TQDM_DISABLE": "1"})
        err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        if status != 0:
            raise SystemExit(f"e2e run on {root} failed:\n{err[-3000:]}")
        run = json.loads((out / "run.json").read_text())
        shutil.rmtree(out)
        t = run["timings_s"]
        for s_ in STAGES:
            stage_t[s_].append(max(float(t.get(s_, 0.0)), 1e-3))
        totals.append(wall)
        c = run["counts"]
        q_images = c["pairs"]  # (query frame, reference session) pairs: one Table I query image each
        ranked = c["ranked_subimages"]
        eval_s = t.get("fusion", 0.0) + t.get("labels_ap_reports", 0.0)
        print(json.dumps({
            "case": f"e2e Table I [{n} frames/session]", "median": wall, "unit": "s", "runs": [wall],
            "peak_rss_mib": usage.ru_maxrss / 1024,
            "ms_per_query_image": round(1000 * wall / max(q_images, 1), 1),
            "ms_per_frame": round(1000 * wall / c["frames"], 1),
            "fusion_labels_ap_share": round(eval_s / wall, 4),
            "notes": (f"{c['frames']} frames 1232x1616 JPEG, {q_images} query images ({c['annotated_frames']} annotated frames x reference sessions), "
                      f"{ranked} ranked subimages; stages s: " + ", ".join(f"{k} {t.get(k, 0):.1f}" for k in STAGES)),
        }), flush=True)
    for s_ in STAGES:
        print(json.dumps({"case": f"scaling: {s_} time vs frames per session", "median": fit_exponent(list(counts), stage_t[s_]), "unit": "exponent",
                          "runs": [], "peak_rss_mib": peak_rss_mib(), "points": {"x": list(counts), "y": stage_t[s_], "xlabel": "frames per session", "ylabel": "s"}}), flush=True)
    print(json.dumps({"case": "scaling: end-to-end time vs frames per session", "median": fit_exponent(list(counts), totals), "unit": "exponent",
                      "runs": [], "peak_rss_mib": peak_rss_mib(), "points": {"x": list(counts), "y": totals, "xlabel": "frames per session", "ylabel": "s"}}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("case")
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    globals()[f"case_{a.case}"](a.quick)


if __name__ == "__main__":
    main()

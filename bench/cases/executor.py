"""Bench case ``executor``."""

from __future__ import annotations

import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from .common import DATA, ROOT, emit, peak_rss_mib


def case_executor(quick: bool) -> None:
    """Descriptor + ranking stages of the fixture: local executor vs Ray with two local workers.

    The cache of a full local run is copied with its descriptor, ranking and fusion stages
    removed, and the run is timed from there (Ray's start-up not included).
    """
    import dataclasses

    from harness.config.assemble import load_config
    from harness.fixture import FixtureSpec, generate
    from harness.pipeline.chain import Pipeline
    from harness.runtime.executors import LocalExecutor, RayExecutor

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
            shutil.copy(base / ".dbl-harness.json", tmp / ".dbl-harness.json")  # the run's own
            for stage in ("descriptor_shards", "descriptors", "ranks", "samples"):
                shutil.rmtree(tmp / "cache" / stage, ignore_errors=True)
            t0 = time.perf_counter()
            Pipeline(cfg, tmp, executor=ex).run()
            runs.append(time.perf_counter() - t0)
            shutil.rmtree(tmp)
        results[name] = runs
        emit(
            f"descriptors+ranks+fusion [{name}]",
            runs,
            "s",
            notes="fixture: 256 frames, 16-frame shards",
        )
    print(
        json.dumps(
            {
                "case": "ray speed-up (local s / ray s)",
                "median": statistics.median(results["local"]) / statistics.median(results["ray"]),
                "unit": "x",
                "runs": [],
                "peak_rss_mib": peak_rss_mib(),
                "notes": "2 local workers on 2 cores",
            }
        ),
        flush=True,
    )

"""The Ray executor: same files and the same table as the local executor, and a worker that dies
mid-shard is retried."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pandas as pd
import pytest

from harness.errors import ConfigError
from harness.pipeline.chain import Pipeline

from ..conftest import no_figures, shared_stages

ray = pytest.importorskip("ray")

MAPPED = ("ingest", "descriptor_shards", "descriptors", "ranks")


@pytest.fixture(scope="module")
def executor():
    from harness.runtime.executors import RayExecutor

    ex = RayExecutor(num_cpus=2)
    yield ex
    ray.shutdown()


#: JSON keys that hold a duration (a report's timing): the one thing a rerun may change.
TIMES = {"seconds", "timings_s", "total_s", "wall_s", "elapsed_s", "build_s"}


def _without_times(doc: object) -> object:
    if isinstance(doc, dict):
        return {k: _without_times(v) for k, v in doc.items() if k not in TIMES}
    if isinstance(doc, list):
        return [_without_times(v) for v in doc]
    return doc


def _json(path: Path) -> object:
    """A JSON file without durations; a manifest also without the sizes and digests of its JSON
    files (a report holds its timing, so its digest moves with it: its content is compared)."""
    import json

    doc = _without_times(json.loads(path.read_text()))
    if path.name == "manifest.json" and isinstance(doc, dict):
        for k in ("files", "sha256"):
            doc[k] = {f: v for f, v in doc.get(k, {}).items() if not f.endswith(".json")}
    return doc


def _files(root: Path, stage: str) -> dict[str, object]:
    """Every file of a stage's cache entries: its bytes (images included), or for JSON its content
    without durations."""
    return {
        str(p.relative_to(root)): _json(p) if p.suffix == ".json" else p.read_bytes()
        for p in sorted((root / "cache" / stage).rglob("*"))
        if p.is_file()
    }


def test_ray_run_equals_local_run(local_run: tuple, executor: object, tmp_path: Path) -> None:
    """A fresh directory, another executor, the same config and seed: the same bytes.

    (Also the determinism check of a run from nothing: every stage but the model, which is not
    mapped over the executor and is copied from the local run, is recomputed here; the model's
    own determinism is the regression's digest of the checkpoint.)
    """
    p, _, out = local_run
    shutil.copytree(out / "cache" / "model", tmp_path / "cache" / "model")
    shutil.copy(out / ".dbl-harness.json", tmp_path / ".dbl-harness.json")
    q = Pipeline(no_figures(p.cfg), tmp_path, executor=executor)
    q.run()
    assert q.ran["descriptor_shards"] > 0 and q.ran["ranks"] == 4 and q.ran.get("model", 0) == 0
    assert q.ran["ingest"] == 4 and q.ran["proposals"] > 0  # the rest from nothing
    # query chunks x reference sessions: a smaller chunk gives more units and the same table
    import dataclasses

    cfg = dataclasses.replace(
        no_figures(p.cfg), retrieval=dataclasses.replace(p.cfg.retrieval, query_frames_per_shard=10)
    )
    chunked = Pipeline(cfg, tmp_path / "chunked", executor=executor)
    shutil.copytree(out / "cache", tmp_path / "chunked" / "cache", dirs_exist_ok=True)
    shutil.rmtree(tmp_path / "chunked" / "cache" / "ranks")
    chunked.run()
    assert chunked.ran["ranks"] > 4
    assert chunked.ran.get("samples", 0) == 0  # same ranks, so the fusion stage is a cache hit
    assert (tmp_path / "chunked" / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
    for stage in MAPPED:
        assert _files(tmp_path, stage) == _files(out, stage), stage
    assert (tmp_path / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()


def test_a_worker_that_dies_mid_shard_is_retried(
    local_run: tuple, executor: object, tmp_path: Path
) -> None:
    from harness.runtime.executors import RayExecutor

    p, _, out = local_run
    shutil.copytree(out / "cache", tmp_path / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / ".dbl-harness.json")
    for stage in ("ranks", "samples"):  # the ranks' units run on Ray (one of them killed)
        shutil.rmtree(tmp_path / "cache" / stage)
    marker = tmp_path / "killed-once"
    faulty = RayExecutor(fault_once=str(marker))  # joins the running local cluster
    q = Pipeline(no_figures(p.cfg), tmp_path, executor=faulty)
    q.run()
    assert marker.exists(), "a worker was killed"
    assert (tmp_path / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
    # a rerun after the crash skips every finished shard
    again = Pipeline(no_figures(p.cfg), tmp_path, executor=faulty)
    again.run()
    assert sum(again.ran.values()) == 0


def test_without_ray_the_error_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    from harness.runtime.executors import make_executor

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(ConfigError, match=r"pip install 'dbl-harness\[ray\]'"):
        make_executor("ray")


def test_the_cli_hands_the_ray_executor_to_the_pipeline(
    local_run: tuple, executor: object, tmp_path: Path
) -> None:
    """As a user types it.

    --executor ray --ray-cpus 2 runs the units on Ray and run.json says so.
    """
    import json

    from harness.cli import main

    from ..conftest import ROOT

    p, _, out = local_run
    # the fixture's cache but its ranks and samples: those units run on Ray here
    shutil.copytree(out / "cache", tmp_path / "o" / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / "o" / ".dbl-harness.json")
    for stage in ("ranks", "samples"):
        shutil.rmtree(tmp_path / "o" / "cache" / stage)
    args = [
        "reproduce",
        "--config",
        str(ROOT / "datasets" / "fixture.toml"),
        "--data-root",
        str(p.cfg.data_root),
        "--out",
        str(tmp_path / "o"),
        "--executor",
        "ray",
        "--ray-cpus",
        "2",
    ]
    assert main(args) == 0
    rec = json.loads((tmp_path / "o" / "run.json").read_text())
    assert rec["executor"]["name"] == "ray" and rec["executor"]["workers"] >= 1
    assert rec["stage_units_run"]["ranks"] == 4 and rec["stage_units_run"].get("model", 0) == 0
    assert (tmp_path / "o" / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
    local = json.loads((out / "run.json").read_text())
    assert local["executor"] == {"name": "local", "workers": 1}


def test_detect_runs_its_chunks_on_ray_and_writes_what_the_local_run_writes(
    local_run: tuple, executor: object, tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """``harness detect --executor ray``: the detect chunks (and the stages) run on Ray workers."""

    from harness.apps.detect import run_detect
    from harness.config.assemble import load_config

    from ..conftest import ROOT, small_null_config

    p, _, out = local_run
    # four chunks: four units mapped over the workers; a small null (its figures are not read)
    toml = small_null_config(ROOT / "datasets" / "fixture-detect.toml", tmp_path)
    toml.write_text(f"{toml.read_text()}\n[detect]\nchunk_frames = 16\n")
    cfg = load_config(toml, data_root=str(p.cfg.data_root))
    runs = {}
    local, ray_out = tmp_path / "local", tmp_path / "ray"
    shutil.copytree(out / "cache" / "ingest", local / "cache" / "ingest")
    shutil.copy(out / ".dbl-harness.json", local / ".dbl-harness.json")
    with shared_stages(tmp_path_factory, "detect-run", local):  # tests/detect's model and ranks
        runs["local"] = run_detect(cfg, "2012-01-22", ["2012-03-31"], local).record
    # the stages before detect's chunks from the local run (their Ray runs are test_ray_run_...)
    shutil.copytree(local / "cache", ray_out / "cache", ignore=shutil.ignore_patterns("detect"))
    shutil.copy(out / ".dbl-harness.json", ray_out / ".dbl-harness.json")
    runs["ray"] = run_detect(cfg, "2012-01-22", ["2012-03-31"], ray_out, executor).record
    query_frames = len(pd.read_parquet(tmp_path / "local" / "frames.parquet"))
    chunks = -(-query_frames // 16)  # the query frames in chunks of chunk_frames = 16
    assert runs["ray"]["stage_units_run"]["detect"] == runs["local"]["stage_units_run"]["detect"]
    assert runs["ray"]["stage_units_run"]["detect"] == chunks == 4
    for f in ("detections.json", "frames.csv"):
        assert (tmp_path / "ray" / f).read_bytes() == (tmp_path / "local" / f).read_bytes(), f
    import json

    def images(name: str) -> list[dict]:  # file names point into each run's own image store
        doc = json.loads((tmp_path / name / "images.json").read_text())
        return [{k: v for k, v in i.items() if k != "file_name"} for i in doc["images"]]

    assert images("ray") == images("local")

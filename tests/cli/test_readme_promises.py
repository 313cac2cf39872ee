"""The README's commands and config features that no other test runs as a user types them.

One small world (``harness fixture`` with the flags the README lists), one config that turns on
the features the README documents but the fixture config leaves at their defaults (``mser``
proposals, ``store_format = "png"``, ``nclt_rotation = "ccw"``, the faiss engine with
``faiss_nlist``/``faiss_nprobe``, a ``train_samples`` budget, ``[report] plots``/``html`` off), one
``harness reproduce --seed`` of it, then the stage commands and ``make reproduce-table CONFIG=...
OUT=...`` on the same run directory (cached: seconds). Each test checks the feature's effect, not
only the exit status.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from harness.cli import main

from ..conftest import ROOT

FLAGS = ["--seed", "3", "--frames", "16", "--width", "96", "--height", "128", "--objects", "4"]

CONFIG = """\
name = "promises"
seed = 0
data_root = "{world}"
annotations = "{world}/annotations.csv"

[[sessions]]
name = "2012-01-22"
season = "WI"
source = "{{data_root}}/nclt"

[[sessions]]
name = "2012-03-31"
season = "SP"
source = "{{data_root}}/ros1/2012-03-31.bag"

[[sessions]]
name = "2012-08-04"
season = "SU"
source = "{{data_root}}/ros2/2012-08-04"

[[sessions]]
name = "2012-11-17"
season = "AU"
source = "{{data_root}}/mcap/2012-11-17.mcap"

[ingest]
store_format = "png"
nclt_rotation = "ccw"

[pairs]
max_yaw_diff_deg = 45.0
max_distance_m = 10.0
queries = "annotated"

[proposals]
methods = ["grid5", "mser"]

[descriptor]
name = "autoencoder"
input_size = 32
input_norm = "per_crop"
batch_size = 16
train_samples = 64
max_train_subimages = 400

[retrieval]
engine = "faiss"
faiss_nlist = 4
faiss_nprobe = 2

[report]
bootstrap = 50
plots = false
html = false
"""


def _run(argv: list[str]) -> str:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0, argv
    return buf.getvalue()


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``harness fixture --out DIR --seed 3 ... --objects 4 --render-scale 2 --all-formats``."""
    out = tmp_path_factory.mktemp("promises") / "world"
    printed = _run(["fixture", "--out", str(out), *FLAGS, "--render-scale", "2", "--all-formats"])
    assert f"fixture written to {out}" in printed
    return out


@pytest.fixture(scope="module")
def run(world: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """``harness reproduce --config CFG --out OUT --seed 1``: (config, out, what it printed)."""
    base = tmp_path_factory.mktemp("promises-run")
    cfg = base / "promises.toml"
    cfg.write_text(CONFIG.format(world=world))
    out = base / "out"
    printed = _run(["reproduce", "--config", str(cfg), "--out", str(out), "--seed", "1"])
    return cfg, out, printed


def test_fixture_flags_shape_the_world(world: Path, tmp_path: Path) -> None:
    """--seed, --frames/--width/--height, --objects, --render-scale and --all-formats each show in
    what was written: another seed gives other bytes, every changed session holds --objects."""
    spec = json.loads((world / "fixture.json").read_text())
    assert spec["spec"]["seed"] == 3 and spec["spec"]["render_scale"] == 2
    assert {p.name for p in world.iterdir()} >= {"nclt", "ros1", "ros2", "mcap", "ros2mcap"}
    assert any((world / "mcaptf").iterdir())  # only --all-formats writes the tf-tree MCAP
    truth = pd.read_csv(world / "truth" / "objects.csv")
    assert truth.groupby("session").size().tolist() == [4, 4, 4]
    img = next((world / "nclt").rglob("*.tiff"))
    assert cv2.imread(str(img)).shape[:2] in ((96, 128), (128, 96))
    other = tmp_path / "seed0"
    _run(["fixture", "--out", str(other), *FLAGS[2:], "--render-scale", "2"])
    assert (other / "annotations.csv").read_bytes() != (world / "annotations.csv").read_bytes()


def test_reproduce_seed_seeds_the_intervals_and_floors_not_the_aps(
    run: tuple[Path, Path, str], tmp_path: Path
) -> None:
    cfg, out, printed = run
    assert "Table I" in printed
    assert json.loads((out / "run.json").read_text())["seed"] == 1
    again = tmp_path / "again"
    shutil.copytree(out / "cache", again / "cache")
    shutil.copy(out / ".dbl-harness.json", again / ".dbl-harness.json")
    _run(["reproduce", "--config", str(cfg), "--out", str(again), "--seed", "2"])
    a = pd.read_parquet(out / "splits" / "summary.parquet")
    b = pd.read_parquet(again / "splits" / "summary.parquet")
    pd.testing.assert_series_equal(a["ap"], b["ap"])  # the same scores
    assert not np.allclose(a["ci_low"], b["ci_low"], equal_nan=True)  # other resamples


def test_png_store_and_ccw_rotation(run: tuple[Path, Path, str], world: Path) -> None:
    """store_format = "png": the stored images are PNG; nclt_rotation = "ccw": an NCLT frame is its
    source image turned counter-clockwise."""
    _, out, _ = run
    stored = list((out / "cache").rglob("images/*"))
    assert stored and all(p.suffix == ".png" for p in stored if p.is_file())
    frames = pd.concat(pd.read_parquet(p) for p in (out / "cache").rglob("frames.parquet"))
    nclt = frames[frames["session"] == "2012-01-22"].iloc[0]
    src = cv2.imread(str(next((world / "nclt").rglob(f"{nclt['utime']}.tiff"))))
    from harness.imagestore import read_image

    uri = str(nclt["image"]).replace("{data_root}", str(world))
    want = cv2.rotate(cv2.cvtColor(src, cv2.COLOR_BGR2RGB), cv2.ROTATE_90_COUNTERCLOCKWISE)
    np.testing.assert_array_equal(read_image(uri), want)


def test_mser_proposals_faiss_ivf_and_the_training_budget(run: tuple[Path, Path, str]) -> None:
    _, out, _ = run
    ranks = pd.read_parquet(out / "ranks.parquet")
    assert set(ranks["proposal_method"]) == {"grid5", "mser"}
    rec = json.loads((out / "run.json").read_text())
    text = json.dumps(rec)
    assert '"faiss_nlist": 4' in text and '"faiss_nprobe": 2' in text
    checked = [int(v) for v in re.findall(r'"faiss_checked": (\d+)', text)]
    equal = [int(v) for v in re.findall(r'"faiss_rank_equal_exact": (\d+)', text)]
    assert checked and sum(checked) > 0 and sum(equal) <= sum(checked)  # faiss ranked, checked
    (model,) = (out / "cache" / "model").glob("*/manifest.json")
    info = json.loads(model.read_text())["info"]
    assert info["steps"] == math.ceil(64 / 16) and info["held_out"] > 0  # the budget, in steps


def test_report_plots_and_html_off(run: tuple[Path, Path, str]) -> None:
    _, out, _ = run
    assert (out / "table1.md").exists()
    assert not (out / "report.html").exists() and not (out / "plots").exists()


def test_stage_commands_as_typed_say_where_their_output_is(run: tuple[Path, Path, str]) -> None:
    """``harness pairs / proposals / rank --config FILE --out DIR`` on a finished run: cached, each
    names its output, and rank's is the run's ranks."""
    cfg, out, _ = run
    before = pd.read_parquet(out / "ranks.parquet")
    for stage in ("pairs", "proposals", "rank"):
        printed = _run([stage, "--config", str(cfg), "--out", str(out)])
        assert str(out) in printed, printed
    pd.testing.assert_frame_equal(pd.read_parquet(out / "ranks.parquet"), before)


def test_make_reproduce_table_with_config_and_out(run: tuple[Path, Path, str]) -> None:
    """``make reproduce-table CONFIG=... OUT=...`` as typed (the run is cached: the tables only)."""
    cfg, out, _ = run
    (out / "table1.md").unlink()
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAKE")}
    proc = subprocess.run(
        ["make", "-s", "reproduce-table", f"CONFIG={cfg}", f"OUT={out}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Table I" in proc.stdout and (out / "table1.md").exists()


def _shift_log_times(src: Path, dst: Path, shift_us: int, topic: str = "") -> None:
    """A copy of a plain MCAP whose log times (of ``topic``, else of every message) lie
    ``shift_us`` after its header stamps."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as fi, open(dst, "wb") as fo:
        reader, w = make_reader(fi), Writer(fo)
        w.start(profile="ros2", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(
                    channel.topic, channel.message_encoding, schemas.get(channel.schema_id, 0)
                )
            t = msg.log_time + (shift_us * 1000 if topic in ("", channel.topic) else 0)
            w.add_message(channels[channel.id], t, msg.data, t, msg.sequence)
        w.finish()


def test_ingest_flags_as_typed(world: Path, tmp_path: Path) -> None:
    """--camera, --image-topic, --pose-topic, --tf-child-frame, --time-source, --max-pose-gap and
    --salvage, each seen in the frame table or the report."""
    log = world / "mcap" / "2012-03-31.mcap"
    shifted = tmp_path / "shifted.mcap"
    _shift_log_times(log, shifted, 300_000)
    common = ["--image-topic", "/camera/image_raw", "--pose-topic", "/pose"]
    _run(["ingest", str(shifted), "--session", "S", "--out", str(tmp_path / "h"), *common])
    _run(
        ["ingest", str(shifted), "--session", "S", "--out", str(tmp_path / "l"), *common]
        + ["--camera", "Cam9", "--time-source", "log", "--max-pose-gap", "0.5"]
    )
    h = pd.read_parquet(tmp_path / "h" / "frames.parquet")
    lt = pd.read_parquet(tmp_path / "l" / "frames.parquet")
    assert len(h) == len(lt) == 16 and set(lt["camera"]) == {"Cam9"}
    assert (lt["utime"].to_numpy() - h["utime"].to_numpy() == 300_000).all()  # log time
    rep = json.loads((tmp_path / "l" / "ingest_report.json").read_text())
    assert rep["topics"]["image"] == "/camera/image_raw" and rep["topics"]["pose"] == ["/pose"]
    # --max-pose-gap: images logged 0.1 s after a pose fall between poses 0.25 s apart
    between = tmp_path / "between.mcap"
    _shift_log_times(log, between, 100_000, "/camera/image_raw")
    for gap, kept in (("0.5", 16), ("0.12", 0)):  # 0.15 s to the next pose: over 0.12
        out = tmp_path / f"g{gap}"
        argv = ["ingest", str(between), "--session", "S", "--out", str(out)]
        assert main([*argv, "--time-source", "log", "--max-pose-gap", gap]) == (0 if kept else 1)
        if kept:
            assert json.loads((out / "ingest_report.json").read_text())["frames_written"] == kept
    tf = world / "mcaptf" / "2012-03-31.mcap"
    _run(["ingest", str(tf), "--session", "S", "--out", str(tmp_path / "t"),
          "--tf-child-frame", "base_link"])  # fmt: skip
    rep = json.loads((tmp_path / "t" / "ingest_report.json").read_text())
    assert rep["pose_frames"] == {"pose_frame": "map", "pose_of": "base_link"}
    assert rep["tf"]["path"] == ["map->base_link"]
    cut = tmp_path / "cut"  # a ROS2 sqlite bag cut at two thirds of its database
    shutil.copytree(world / "ros2" / "2012-08-04", cut)
    (db,) = cut.glob("*.db3")
    db.write_bytes(db.read_bytes()[: db.stat().st_size * 2 // 3])
    argv = ["ingest", str(cut), "--session", "S", "--out", str(tmp_path / "c")]
    assert main(argv) == 1  # damaged: one ERROR line, pointing at --salvage
    _run([*argv, "--salvage"])
    rep = json.loads((tmp_path / "c" / "ingest_report.json").read_text())
    assert 0 < rep["frames_written"] < 16 and "salvaged" in rep

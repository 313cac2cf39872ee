"""Nothing lost, nothing silently wrong: one test per defect a new user hit (issue 11, items 1-11).

Each case goes through the CLI as a user types it where it can; bad input must give one
``ERROR:`` line, exit 1, and leave nothing partial behind.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.cli import main
from harness.config import IngestConfig, SessionConfig, load_config
from harness.errors import ConfigError, CorruptLogError, HarnessError, IngestError
from harness.fixture import writers as W
from harness.ingest import ingest_session, load_frames
from harness.records import Pose
from harness.runner import Pipeline

from .conftest import ROOT, one_error

FIXTURE_TOML = ROOT / "datasets" / "fixture.toml"
TINY = ["--frames", "6", "--width", "32", "--height", "40", "--loop-scale", "1.0"]


_err = one_error


def _config(tmp: Path, text_edit: tuple[str, str] | None = None, extra: str = "") -> Path:
    text = FIXTURE_TOML.read_text()
    if text_edit:
        assert text_edit[0] in text
        text = text.replace(*text_edit)
    p = tmp / "c.toml"
    p.write_text(text + extra)
    return p


def _log(tmp: Path, fmt: str, poses: list[Pose] | None = None, n: int = 6, **kw: object) -> Path:
    rgb = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(n)]
    poses = poses or [
        Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(2 * n)
    ]
    if fmt == "mcap":
        path = tmp / "log.mcap"
        W.write_mcap(path, frames, poses, **kw)  # type: ignore[arg-type]
    elif fmt == "ros1":
        path = tmp / "log.bag"
        W.write_ros1(path, frames, poses)
    else:
        path = tmp / "bag"
        W.write_ros2(path, frames, poses, storage="sqlite3", **kw)  # type: ignore[arg-type]
    return path


# ------------------------------------------------------------------ 1. the fixture generator and
# data_root


def test_1_fixture_generation_never_touches_an_existing_data_root(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    real = tmp_path / "x" / "ground_truth" / "groundtruth_2012-01-22.csv"
    real.parent.mkdir(parents=True)
    real.write_text("real\n")
    assert (
        main(
            [
                "pairs",
                "--config",
                str(FIXTURE_TOML),
                "--data-root",
                str(tmp_path / "x"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 1
    )
    err = _err(capsys)
    assert "data_root exists and holds no generated fixture" in err and "generate = false" in err
    assert real.read_text() == "real\n" and sorted(p.name for p in (tmp_path / "x").rglob("*")) == [
        "ground_truth",
        real.name,
    ]


# ------------------------------------------------------------------ 2. --out never replaces a
# foreign directory


def test_2_ingest_refuses_a_foreign_out_and_replaces_its_own_only_with_force(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    log = _log(tmp_path, "mcap")
    d = tmp_path / "d"
    d.mkdir()
    (d / "thesis.txt").write_text("keep")
    assert main(["ingest", str(log), "--session", "S", "--out", str(d)]) == 1
    assert "holds files the harness did not write (e.g. 'thesis.txt')" in _err(capsys)
    assert (d / "thesis.txt").read_text() == "keep" and sorted(p.name for p in d.iterdir()) == [
        "thesis.txt"
    ]
    out = tmp_path / "o"
    assert main(["ingest", str(log), "--session", "S", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["ingest", str(log), "--session", "S", "--out", str(out)]) == 1
    assert "pass --force" in _err(capsys)
    assert main(["ingest", str(log), "--session", "S", "--out", str(out), "--force"]) == 0
    capsys.readouterr()
    assert (
        main(["ingest", str(log), "--session", "S", "--out", str(d), "--force"]) == 1
    )  # --force never covers a foreign dir
    assert (d / "thesis.txt").read_text() == "keep"


def test_2_out_as_the_working_directory_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = _log(tmp_path, "mcap")
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.md").write_text("mine")
    monkeypatch.chdir(work)
    for out in (".", str(work), str(tmp_path)):
        assert main(["ingest", str(log), "--session", "S", "--out", out]) == 1
        assert "working directory" in _err(capsys)
    assert (work / "notes.md").read_text() == "mine" and log.exists()


def test_2_fixture_export_and_reproduce_refuse_foreign_directories(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    d = tmp_path / "d"
    d.mkdir()
    (d / "keep.txt").write_text("keep")
    assert main(["fixture", "--out", str(d), *TINY]) == 1
    _err(capsys)
    fx = tmp_path / "fx"
    assert main(["fixture", "--out", str(fx), *TINY]) == 0
    capsys.readouterr()
    assert main(["fixture", "--out", str(fx), *TINY]) == 1 and "--force" in _err(capsys)
    assert main(["fixture", "--out", str(fx), *TINY, "--force"]) == 0
    capsys.readouterr()
    frames = tmp_path / "frames.parquet"
    pd.DataFrame({"session": [], "camera": [], "utime": []}).to_parquet(frames)
    pairs = tmp_path / "pairs.parquet"
    pd.DataFrame({"q_session": [], "q_camera": [], "q_utime": []}).to_parquet(pairs)
    assert (
        main(
            [
                "annotations",
                "export",
                "--pairs",
                str(pairs),
                "--frames",
                str(frames),
                "--out",
                str(d),
            ]
        )
        == 1
    )
    _err(capsys)
    assert (
        main(["reproduce", "--config", str(FIXTURE_TOML), "--data-root", str(fx), "--out", str(d)])
        == 1
    )
    assert "never writes into such a directory" in _err(capsys)
    assert sorted(p.name for p in d.iterdir()) == ["keep.txt"]
    ann_out = tmp_path / "ann.csv"
    ann_out.write_text("precious\n")
    assert (
        main(["annotations", "import", "coco", str(tmp_path / "none.json"), "--out", str(ann_out)])
        == 1
    )
    assert "pass --force" in _err(capsys) and ann_out.read_text() == "precious\n"


# ------------------------------------------------------------------ 3. flags and config keys are
# honoured


def test_3_fusion_methods_are_honoured(local_run: tuple, tmp_path: Path) -> None:
    p, _, _out = local_run
    cfg = dataclasses.replace(
        p.cfg,
        fusion=dataclasses.replace(p.cfg.fusion, methods=("score_max", "rank_fusion", "random")),
    )
    shutil.copytree(_out / "cache", tmp_path / "o" / "cache")  # only fusion and reports rerun
    shutil.copy(_out / ".dbl-harness.json", tmp_path / "o" / ".dbl-harness.json")
    rec = Pipeline(cfg, tmp_path / "o").run()
    assert list(rec["table"].index) == [
        "rank_fusion",
        "score_max",
        "random",
    ]  # SPEC order, whatever the config's order
    assert pd.read_csv(tmp_path / "o" / "table1.csv")["method"].tolist() == [
        "rank_fusion",
        "score_max",
        "random",
    ]
    cols = pd.read_parquet(tmp_path / "o" / "splits" / "roc_max_0.01.parquet").columns
    assert {"loc_rank_fusion", "loc_score_max", "loc_random"} <= set(
        cols
    ) and "loc_score_sum" not in cols


def test_3_ray_flags_need_the_ray_executor(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert (
        main(
            [
                "reproduce",
                "--config",
                str(FIXTURE_TOML),
                "--out",
                str(tmp_path / "o"),
                "--address",
                "auto",
            ]
        )
        == 1
    )
    assert "--address and --ray-cpus need --executor ray" in _err(capsys)
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------ 4. wrong tables with exit 0


@pytest.mark.parametrize(
    ("edit", "extra", "message"),
    [
        (
            None,
            "\n[splits]\nneg_sob = [1.0, 0.4]\n",
            r"\[splits\] neg_sob = \[1.0, 0.4\] is out of range",
        ),
        (None, "\n[splits]\nroc_max = []\n", r"\[splits\] roc_max = \[\] is out of range"),
        (
            ("epochs = 6", "epochs = -1"),
            "",
            r"\[descriptor\] epochs = -1 is out of range; allowed: >= 1",
        ),
        (
            ("epochs = 6", 'epochs = "six"'),
            "",
            r"\[descriptor\] epochs: expected an integer, got 'six'",
        ),
        (("bootstrap = 200", "bootstrap = -5"), "", r"\[report\] bootstrap = -5 is out of range"),
        (
            ("bootstrap = 200", "bootstrap = 200\nci = 1.5"),
            "",
            r"\[report\] ci = 1.5 is out of range; allowed: \(0, 1\)",
        ),
        (
            ("max_distance_m = 10.0", "max_distance_m = -3.0"),
            "",
            r"\[pairs\] max_distance_m = -3.0 is out of range",
        ),
        (
            ("max_distance_m = 10.0", 'max_distance_m = "far"'),
            "",
            r"max_distance_m: expected a number, got 'far'",
        ),
        (
            None,
            '\n[fusion]\nmethods = ["rank_fusion", "magic"]\n',
            r"\[fusion\] methods = \['rank_fusion', 'magic'\] is out of range",
        ),
        (
            None,
            "\n[retrieval]\ngt_radius_m = -1.0\n",
            r"\[retrieval\] gt_radius_m = -1.0 is out of range",
        ),
    ],
)
def test_4_bad_config_values_fail_at_load(
    tmp_path: Path, edit: tuple | None, extra: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(_config(tmp_path, edit, extra))


def test_4_bad_config_is_one_error_line_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    cfg = _config(tmp_path, ("bootstrap = 200", "bootstrap = 200\nci = 1.5"))
    assert main(["reproduce", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 1
    assert "ci = 1.5" in _err(capsys) and not (tmp_path / "o").exists()


def test_4_annotations_without_a_change_frame_are_an_error(
    default_world: Path, tmp_path: Path
) -> None:
    ann = pd.read_csv(ROOT / "annotations" / "fixture.csv")
    ann = ann[ann["status"] == "no-change"]
    ann.to_csv(tmp_path / "nochange.csv", index=False)
    cfg = load_config(FIXTURE_TOML, data_root=str(default_world))
    cfg = dataclasses.replace(cfg, annotations=tmp_path / "nochange.csv")
    with pytest.raises(HarnessError, match="no frame is annotated 'change'"):
        Pipeline(cfg, tmp_path / "o").run()


def test_4_imported_ranks_with_foreign_ids_are_an_error(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    p, _, out = local_run
    ranks = pd.read_parquet(out / "ranks.parquet")
    frames = pd.read_parquet(next((out / "cache" / "frames").glob("*/frames.parquet")))
    rows = []
    for r in ranks.head(40).itertuples():
        ids = (
            frames.loc[frames["session"] == r.r_session, "utime"].to_numpy()[:5] * 1000
        )  # nanoseconds
        rows.append(
            {
                "q_session": r.q_session,
                "q_camera": r.q_camera,
                "q_utime": r.q_utime,
                "method": r.method,
                "box_id": r.box_id,
                "x1": r.x1,
                "y1": r.y1,
                "x2": r.x2,
                "y2": r.y2,
                "r_session": r.r_session,
                "ranked": " ".join(map(str, ids)),
                "L": 64,
            }
        )
    pd.DataFrame(rows).to_csv(tmp_path / "ext.csv", index=False)
    args = [
        "reproduce",
        "--config",
        str(FIXTURE_TOML),
        "--data-root",
        str(p.cfg.data_root),
        "--out",
        str(tmp_path / "o"),
        "--import",
        str(tmp_path / "ext.csv"),
    ]
    assert main(args) == 1
    assert "40 rows list reference ids that are not frames of their reference session" in _err(
        capsys
    )


# ------------------------------------------------------------------ 5. non-finite poses and
# quaternions


def test_5_non_finite_poses_are_dropped_and_counted(tmp_path: Path) -> None:
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(12)]
    poses[3] = dataclasses.replace(poses[3], x=float("nan"))
    poses[7] = dataclasses.replace(poses[7], y=float("inf"))
    path = _log(tmp_path, "mcap", poses)
    rep = ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")
    assert rep["dropped"]["non_finite_pose"] == 2
    df = load_frames(tmp_path / "o" / "frames.parquet")
    assert np.isfinite(df[["x", "y", "z", "roll", "pitch", "yaw"]].to_numpy()).all()


def test_5_inf_in_nclt_ground_truth_is_dropped_and_counted(
    small_world: Path, tmp_path: Path
) -> None:
    root = tmp_path / "nclt"
    shutil.copytree(small_world / "nclt", root)
    gt = next((root / "ground_truth").glob("*.csv"))
    session = gt.stem.replace("groundtruth_", "")
    lines = gt.read_text().splitlines()
    parts = lines[5].split(",")
    parts[2] = "inf"
    lines[5] = ",".join(parts)
    gt.write_text("\n".join(lines) + "\n")
    rep = ingest_session(
        SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
    )
    base = ingest_session(
        SessionConfig(name=session, source=str(small_world / "nclt")),
        IngestConfig(),
        tmp_path / "b",
    )
    assert (
        rep["dropped"]["groundtruth_non_finite_rows"]
        == base["dropped"]["groundtruth_non_finite_rows"] + 1
    )


def _quat_log(
    tmp: Path,
    q: tuple[float, float, float, float] | None = None,
    pose_utimes: list[int] | None = None,
) -> Path:
    """An MCAP (written by the real mcap and CDR libraries, in this message order) whose 5th pose
    message carries quaternion ``q``; ``pose_utimes`` replaces the pose stamps."""
    from mcap.writer import Writer

    ts = W.ROS2
    path = tmp / "q.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        chans = {}
        for topic, typ in (
            ("/image", "sensor_msgs/msg/Image"),
            ("/pose", "geometry_msgs/msg/PoseStamped"),
        ):
            msgdef, _ = ts.generate_msgdef(typ, ros_version=2)
            sid = w.register_schema(name=typ, encoding="ros2msg", data=msgdef.encode())
            chans[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
        rgb = np.zeros((4, 4, 3), np.uint8)
        for i in range(8):
            t = 1_000_000 + i * 50_000
            msg = W.pose_stamped_msg(
                ts, Pose(pose_utimes[i] if pose_utimes else t, float(i), 0.0, 0.0, 0.0, 0.0, 0.0)
            )
            if i == 4 and q is not None:
                (
                    msg.pose.orientation.x,
                    msg.pose.orientation.y,
                    msg.pose.orientation.z,
                    msg.pose.orientation.w,
                ) = q
            w.add_message(
                chans["/pose"],
                log_time=t * 1000,
                data=bytes(ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped")),
                publish_time=t * 1000,
            )
            if i % 2:
                im = W.image_msg(ts, t, rgb, "rgb8")
                w.add_message(
                    chans["/image"],
                    log_time=t * 1000,
                    data=bytes(ts.serialize_cdr(im, "sensor_msgs/msg/Image")),
                    publish_time=t * 1000,
                )
        w.finish()
    return path


def test_5_zero_or_euler_quaternions_are_rejected_with_message_and_norm(tmp_path: Path) -> None:
    for q, norm in (((0.0, 0.0, 0.0, 0.0), "norm 0"), ((0.1, 0.2, 1.5, 0.0), "norm 1.51658")):
        with pytest.raises(IngestError, match=rf"/pose message 5.*{norm}, not 1 .*Euler angles"):
            ingest_session(
                SessionConfig(name="s", source=str(_quat_log(tmp_path, q))),
                IngestConfig(),
                tmp_path / "o",
            )
        assert not (tmp_path / "o").exists()


def test_5_nearly_unit_quaternions_are_normalised_and_counted(tmp_path: Path) -> None:
    rep = ingest_session(
        SessionConfig(name="s", source=str(_quat_log(tmp_path, (0.0, 0.0, 0.0, 1.0005)))),
        IngestConfig(),
        tmp_path / "o",
    )
    assert rep["normalised"]["quaternion_normalised"] == 1 and rep["frames_written"] == 4


# ------------------------------------------------------------------ 6. faults: debris, disk full,
# damaged caches


def test_6_temporaries_of_a_killed_run_are_removed_and_the_lock_refuses_a_second_run(
    local_run: tuple, tmp_path: Path
) -> None:
    from harness.outdirs import run_lock

    p, _, out = local_run
    q = Pipeline(p.cfg, tmp_path / "o")
    debris = tmp_path / "o" / "cache" / "model" / ".abc123.dbl-harness-x7y8z9ab.tmp"
    stray = tmp_path / "o" / ".table1.csv.dbl-harness-x1y2z3w4.tmp"
    with run_lock(
        tmp_path / "o"
    ):  # another run holds the lock while a killed run's debris lies there
        debris.mkdir(parents=True)
        (debris / "train_crops.npy").write_bytes(b"\0" * 1000)
        stray.write_text("half")
        with pytest.raises(HarnessError, match=rf"another harness run \(pid {os.getpid()}\)"):
            q.run()
        assert debris.exists()  # nothing is removed while another run holds the lock
    shutil.copytree(out / "cache", tmp_path / "o" / "cache", dirs_exist_ok=True)
    q.run()
    assert not debris.exists() and not stray.exists()


def test_6_disk_full_and_read_only_are_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    import harness.cli as cli

    for code, words in ((errno.ENOSPC, "free disk space"), (errno.EROFS, "read-only")):

        def boom(args: object, code: int = code) -> int:
            raise OSError(code, os.strerror(code), str(tmp_path / "o" / "cache" / "x"))

        monkeypatch.setattr(cli, "cmd_reproduce", boom)
        parser = cli.build_parser()
        monkeypatch.setattr(cli, "build_parser", lambda p=parser: p)
        for sp in parser._subparsers._group_actions[0].choices.values():  # type: ignore[union-attr]
            if sp.prog.endswith("reproduce"):
                sp.set_defaults(func=boom)
        assert main(["reproduce", "--config", str(FIXTURE_TOML), "--out", str(tmp_path / "o")]) == 1
        err = _err(capsys)
        assert str(tmp_path / "o" / "cache" / "x") in err and words in err


def test_6_memmaps_reserve_their_blocks(tmp_path: Path) -> None:
    """A training-crop or descriptor memmap is allocated up front (ENOSPC, not SIGBUS later)."""
    from harness.cache import open_memmap_reserved

    arr = open_memmap_reserved(tmp_path / "a.npy", np.uint8, (64, 64, 64, 3))
    assert os.stat(tmp_path / "a.npy").st_blocks * 512 >= 64 * 64 * 64 * 3
    del arr


def test_6_a_damaged_cache_entry_is_rebuilt(local_run: tuple, tmp_path: Path) -> None:
    p, _, out = local_run
    q = Pipeline(p.cfg, tmp_path / "o")
    shutil.copytree(out / "cache", tmp_path / "o" / "cache", dirs_exist_ok=True)
    victim = next((tmp_path / "o" / "cache" / "samples").glob("*/samples.parquet"))
    victim.write_bytes(victim.read_bytes()[:100])
    q.run()
    assert q.ran.get("samples") == 1 and sum(v for k, v in q.ran.items() if k != "samples") == 0
    assert (tmp_path / "o" / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()


def test_6_corrupt_zstd_chunk_in_mcap_is_a_clear_error(tmp_path: Path) -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    frames = [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(40)]
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(80)]
    path = tmp_path / "z.mcap"
    W.write_mcap(path, frames, poses)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3 : len(raw) // 3 + 64] = b"\xa5" * 64
    path.write_bytes(bytes(raw))
    with pytest.raises((CorruptLogError, IngestError), match=r"z\.mcap"):
        ingest_session(SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "o")


# ------------------------------------------------------------------ 7. moving an output directory;
# '#' in paths


def test_7_a_moved_run_directory_resumes_without_reading_the_old_place(
    local_run: tuple, tmp_path: Path
) -> None:
    p, _, out = local_run
    shutil.copytree(out, tmp_path / "first")
    shutil.move(str(tmp_path / "first"), str(tmp_path / "moved"))
    frames = pd.read_parquet(
        next((tmp_path / "moved" / "cache" / "frames").glob("*/frames.parquet"))
    )
    assert all(u.startswith(("{out}/", "{data_root}/")) for u in frames["image"])
    q = Pipeline(p.cfg, tmp_path / "moved")
    q.run()
    assert sum(q.ran.values()) == 0
    assert (tmp_path / "moved" / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()


def test_7_a_hash_in_data_and_out_paths_works(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    cfg = _config(
        tmp_path, ("frames = 64\nwidth = 120\nheight = 160", "frames = 8\nwidth = 48\nheight = 64")
    )
    data, out = tmp_path / "da#ta", tmp_path / "ou#t"
    assert (
        main(["proposals", "--config", str(cfg), "--data-root", str(data), "--out", str(out)]) == 0
    )
    assert "edges" in capsys.readouterr().out


# ------------------------------------------------------------------ 8. --salvage for ROS1 and ROS2
# bags


@pytest.mark.parametrize("compression", ["none", "bz2", "lz4"])
def test_8_salvage_keeps_the_frames_of_a_truncated_ros1_bag(
    tmp_path: Path, compression: str
) -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    path = tmp_path / "full.bag"
    poses = [Pose(1_000_000 + i * 50_000, float(i), 0, 0, 0, 0, 0) for i in range(40)]
    frames = [W.LogFrame(p.utime, rgb) for p in poses[1::2]]
    W.write_ros1(
        path, frames, poses, compression=compression, chunk_bytes=20_000
    )  # several chunks: whole ones survive
    bad = tmp_path / "trunc.bag"
    bad.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    with pytest.raises(CorruptLogError, match=r"Rerun with --salvage"):
        ingest_session(SessionConfig(name="s", source=str(bad)), IngestConfig(), tmp_path / "o")
    rep = ingest_session(
        SessionConfig(name="s", source=str(bad)), IngestConfig(salvage=True), tmp_path / "o"
    )
    assert 0 < rep["frames_written"] < 20 and "salvaged" in rep


def test_8_salvage_of_a_ros2_bag_keeps_what_sqlite_can_read_or_says_it_cannot(
    tmp_path: Path,
) -> None:
    path = _log(tmp_path, "ros2", n=30)
    db = next(path.glob("*.db3"))
    (path / "metadata.yaml").unlink()  # rosbags cannot open the bag: the sequential reader must
    rep = ingest_session(
        SessionConfig(name="s", source=str(path), format="ros2"),
        IngestConfig(salvage=True),
        tmp_path / "o",
    )
    assert rep["frames_written"] == 30
    raw = db.read_bytes()
    db.write_bytes(raw[: len(raw) // 2])
    try:
        rep = ingest_session(
            SessionConfig(name="s", source=str(path), format="ros2"),
            IngestConfig(salvage=True),
            tmp_path / "o2",
        )
        assert rep["frames_written"] < 30
    except CorruptLogError as err:
        assert "--salvage was given" in str(err) and "Rerun with --salvage" not in str(err)


def test_8_a_truncated_mcap_is_called_damaged_not_empty(tmp_path: Path) -> None:
    path = _log(tmp_path, "mcap")
    bad = tmp_path / "t.mcap"
    bad.write_bytes(path.read_bytes()[:40])
    with pytest.raises(CorruptLogError, match=r"truncated or corrupt") as ei:
        ingest_session(
            SessionConfig(name="s", source=str(bad)), IngestConfig(salvage=True), tmp_path / "o"
        )
    assert "empty" not in str(ei.value) and "Rerun with --salvage" not in str(ei.value)


# ------------------------------------------------------------------ 9. line numbers as an editor
# counts them


def test_9_annotation_errors_count_blank_lines(tmp_path: Path) -> None:
    from harness.annotations import load_annotations
    from harness.errors import AnnotationError

    p = tmp_path / "a.csv"
    p.write_text(
        "session,camera,utime,status,x1,y1,x2,y2,label\ns,c,1,no-change,,,,,\n\n\ns,c,2,maybe,,,,,\n"
    )
    with pytest.raises(AnnotationError, match=r"line 5: status must be"):
        load_annotations(p)


def test_9_nclt_ground_truth_errors_name_the_csv_line(small_world: Path, tmp_path: Path) -> None:
    root = tmp_path / "nclt"
    shutil.copytree(small_world / "nclt", root)
    gt = next((root / "ground_truth").glob("*.csv"))
    session = gt.stem.replace("groundtruth_", "")
    lines = gt.read_text().splitlines()
    nan_lines = [i + 1 for i, line in enumerate(lines) if "nan" in line.lower()]
    k = max(nan_lines) + 3  # a line after the NaN rows, so a row index would differ from the line
    parts = lines[k - 1].split(",")
    parts[0] = "5"
    lines[k - 1] = ",".join(parts)
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError, match=rf"line {k} at utime 5 comes after line {k - 1}"):
        ingest_session(
            SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
        )


def test_9_pose_message_numbers_are_one_based(tmp_path: Path) -> None:
    stamps = [1_000_000 + i * 50_000 for i in range(8)]
    stamps[2] = 10  # the third pose message goes back in time
    path = _quat_log(tmp_path, pose_utimes=stamps)
    with pytest.raises(
        IngestError, match=r"message 3 at utime 10 comes after message 2 at utime 1050000"
    ):
        ingest_session(
            SessionConfig(name="s", source=str(path)),
            IngestConfig(time_source="header"),
            tmp_path / "o",
        )


# ------------------------------------------------------------------ 10. stale files, modes,
# truncated JPEG


def test_10_a_rerun_with_fewer_splits_removes_stale_split_files(
    local_run: tuple, tmp_path: Path
) -> None:
    p, _, out = local_run
    shutil.copytree(out, tmp_path / "o", dirs_exist_ok=True)
    cfg = dataclasses.replace(p.cfg, splits=dataclasses.replace(p.cfg.splits, roc_max=(0.01, 0.05)))
    Pipeline(cfg, tmp_path / "o").run()
    assert sorted(f.name for f in (tmp_path / "o" / "splits").glob("roc_max_*")) == [
        "roc_max_0.01.parquet",
        "roc_max_0.05.parquet",
    ]
    assert sorted(f.name for f in (tmp_path / "o" / "plots").glob("pr_*")) == [
        "pr_roc_max_0.01.png",
        "pr_roc_max_0.05.png",
    ]
    assert pd.read_csv(tmp_path / "o" / "table1.csv").columns.tolist() == ["method", "0.01", "0.05"]


def test_10_outputs_take_their_mode_from_the_umask(local_run: tuple) -> None:
    from harness.cache import _UMASK

    _, _, out = local_run
    for f in ("table1.csv", "splits/summary.parquet", "run.json"):
        assert (out / f).stat().st_mode & 0o777 == 0o666 & ~_UMASK, f
    assert (out / "splits").stat().st_mode & 0o777 == 0o777 & ~_UMASK
    entry = next((out / "cache" / "ranks").iterdir())
    assert entry.stat().st_mode & 0o777 == 0o777 & ~_UMASK


def test_10_verify_images_drops_a_truncated_jpeg(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    import sqlite3

    rgb = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    path = tmp_path / "bag"
    W.write_ros2(
        path,
        [W.LogFrame(1_000_000 + i * 100_000, rgb) for i in range(6)],
        [Pose(1_000_000 + i * 50_000, float(i), 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(12)],
        storage="sqlite3",
        image="compressed",
    )
    db = next(path.glob("*.db3"))
    con = sqlite3.connect(db)
    tid = con.execute(
        "SELECT id FROM topics WHERE type = 'sensor_msgs/msg/CompressedImage'"
    ).fetchone()[0]
    rid, data = con.execute(
        "SELECT id, data FROM messages WHERE topic_id = ? ORDER BY id LIMIT 1 OFFSET 2", (tid,)
    ).fetchone()
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    msg = ts.deserialize_cdr(bytes(data), "sensor_msgs/msg/CompressedImage")
    msg.data = msg.data[: int(len(msg.data) * 0.8)]  # the header survives, the body does not
    con.execute(
        "UPDATE messages SET data = ? WHERE id = ?",
        (bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage")), rid),
    )
    con.commit()
    con.close()
    rep = ingest_session(
        SessionConfig(name="s", source=str(path)), IngestConfig(), tmp_path / "plain"
    )
    assert rep["frames_written"] == 6  # the header alone looks fine
    assert (
        main(
            ["ingest", str(path), "--session", "s", "--out", str(tmp_path / "v"), "--verify-images"]
        )
        == 0
    )
    rep = json.loads((tmp_path / "v" / "ingest_report.json").read_text())
    assert rep["dropped"]["corrupt_image"] == 1 and rep["frames_written"] == 5


# ------------------------------------------------------------------ 11. stage keys carry the code's
# fingerprint


def test_11_stage_keys_change_with_the_code(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import harness
    import harness.cache as cache

    pkg = Path(harness.__file__).parent
    shutil.copytree(pkg, tmp_path / "harness", ignore=shutil.ignore_patterns("__pycache__"))
    before = cache.code_fingerprint(tmp_path / "harness")
    assert before == cache.CODE_FINGERPRINT  # the copy hashes like the installed package
    fusion = tmp_path / "harness" / "fusion.py"
    fusion.write_text(
        fusion.read_text().replace(
            "cover.sum(1) * (cover * inv[None, :]).sum(1)",
            "(cover * inv[None, :]).sum(1)",
        )
    )
    after = cache.code_fingerprint(tmp_path / "harness")
    assert after != before
    html = (
        tmp_path / "harness" / "report_html.py"
    )  # the report page is rebuilt on every run: no stage depends on it
    html.write_text(html.read_text() + "\n# an edit\n")
    assert cache.code_fingerprint(tmp_path / "harness") == after
    sc = cache.StageCache(tmp_path / "c")
    k1 = sc.key("samples", "x")
    monkeypatch.setattr(cache, "CODE_FINGERPRINT", after)
    assert sc.key("samples", "x") != k1

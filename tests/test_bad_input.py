"""Bad input across the commands, as a user types it: nothing silently wrong, no traceback.

Each case: one ``ERROR:`` line naming the value and what is wrong, exit 1, or for a bug the last
resort's one line and exit 2 (flags and config values that once failed deep in a stage, an output
below a file, annotation and ground-truth files with bad lines, a broken tf tree).
"""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from harness import cli
from harness.cli import main

from .safety_common import FIXTURE_TOML, TINY, _config, _err, _log


@pytest.mark.parametrize(
    ("flag", "value", "needle"),
    [
        ("--max-pose-gap", "nan", "--max-pose-gap = nan is out of range"),
        ("--max-pose-gap", "inf", "--max-pose-gap = inf is out of range"),
        ("--max-tf-gap", "nan", "--max-tf-gap = nan is out of range"),
        ("--max-pose-gap", "0", "--max-pose-gap = 0.0 is out of range"),
    ],
)
def test_ingest_gap_flags_go_through_the_config_checks(
    tmp_path: Path, capsys: pytest.CaptureFixture, flag: str, value: str, needle: str
) -> None:
    log = _log(tmp_path, "mcap")
    argv = ["ingest", str(log), "--session", "s1", "--out", str(tmp_path / "o"), flag, value]
    assert main(argv) == 1
    err = _err(capsys)
    assert needle in err and "finite" in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("edit", "extra", "needle"),
    [
        (("[descriptor]\n", "[descriptor]\nseed = -1\n"), "", "[descriptor] seed = -1 is out"),
        (None, "\n[projection]\nseed = -1\n", "[projection] seed = -1 is out of range"),
        (("seed = 0\nframes", "seed = -1\nframes"), "", "[fixture] seed = -1 is out of range"),
        (("seed = 0\ndata_root", "seed = -1\ndata_root"), "", "seed = -1: expected an integer"),
        (
            None,
            "\n[retrieval]\ndb_stride_m = 10.0\ngt_radius_m = 2.0\n",
            "[retrieval] gt_radius_m = 2.0 is out of range; allowed: at least half of "
            "db_stride_m = 10",
        ),
        (("loop_scale = 1.5", "loop_scale = inf"), "", "[fixture] loop_scale: inf is not a finite"),
        (
            ("[report]\n", "[report]\nchance_draws = 100\n"),
            "",
            "[report] chance_draws = 100 is out",
        ),
    ],
)
def test_config_values_that_were_accepted_or_failed_deep_in_a_stage(
    tmp_path: Path, capsys: pytest.CaptureFixture, edit: tuple | None, extra: str, needle: str
) -> None:
    cfg = _config(tmp_path, edit, extra)
    assert main(["pairs", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 1
    assert needle in _err(capsys)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--loop-scale", "0"], "--loop-scale = 0.0 is out of range"),
        (["--seed", "-1"], "--seed = -1 is out of range"),
        (["--objects", "-1"], "--objects = -1 is out of range"),
        (["--frames", "0"], "--frames = 0 is out of range"),
    ],
)
def test_fixture_flags_go_through_the_config_checks_and_name_the_flag(
    tmp_path: Path, capsys: pytest.CaptureFixture, flags: list[str], needle: str
) -> None:
    argv = ["fixture", "--out", str(tmp_path / "fx"), *TINY, *flags]
    assert main(argv) == 1
    assert needle in _err(capsys)
    assert not (tmp_path / "fx").exists()


@pytest.mark.parametrize(("flags", "needle"), [
    (["--top", "-1"], "--top = -1 is out of range; allowed: >= 0 places"),
    (["--executor", "ray", "--ray-cpus", "0"], "--ray-cpus 0: must be >= 1"),
])  # fmt: skip
def test_detect_flags_are_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture, flags: list[str], needle: str
) -> None:
    argv = ["detect", "--config", str(FIXTURE_TOML), "--map", "2012-01-22", "--query",
            "2012-03-31", "--out", str(tmp_path / "d"), *flags]  # fmt: skip
    assert main(argv) == 1
    assert needle in _err(capsys)
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("command", ["pairs", "reproduce", "ingest", "fixture"])
def test_out_below_a_regular_file_is_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, command: str
) -> None:
    blocker = tmp_path / "file.txt"
    blocker.write_text("a user's file")
    out = str(blocker / "o")
    argv = {
        "pairs": ["pairs", "--config", str(FIXTURE_TOML), "--out", out],
        "reproduce": ["reproduce", "--config", str(FIXTURE_TOML), "--out", out],
        "ingest": ["ingest", "--config", str(FIXTURE_TOML), "--out", out],
        "fixture": ["fixture", "--out", out, *TINY],
    }[command]
    assert main(argv) == 1
    err = _err(capsys)
    assert "file.txt" in err and "not a directory" in err, err
    assert blocker.read_text() == "a user's file"


def test_an_unexpected_error_is_one_internal_error_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The last resort: a bug anywhere is one line naming the command, exit 2; -v adds the
    traceback."""

    def boom(args: object) -> int:
        raise ZeroDivisionError("division by zero\nsecond line")

    monkeypatch.setattr(cli.common, "run_config", boom)
    argv = ["pairs", "--config", str(FIXTURE_TOML), "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = _err(capsys)
    assert err.strip() == (
        "ERROR: internal error in pairs: ZeroDivisionError: division by zero "
        "(run with -v for the traceback)"
    )
    assert main(["-v", *argv]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_an_os_error_the_cli_does_not_name_is_the_internal_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    def fail(args: object) -> int:
        raise OSError(errno.EIO, "Input/output error", "/dev/sdz")

    monkeypatch.setattr(cli.common, "run_config", fail)
    assert main(["pairs", "--config", str(FIXTURE_TOML), "--out", str(tmp_path / "o")]) == 2
    assert "internal error in pairs: OSError" in _err(capsys)


def _annotations(tmp_path: Path, body: bytes) -> Path:
    p = tmp_path / "ann.csv"
    p.write_bytes(b"session,camera,utime,status,x1,y1,x2,y2,label\n" + body)
    return p


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        (b"2012-03-31,Cam5,1333195206000000,no-change,,,,,caf\xe9\n", "line 2: not UTF-8 text"),
        (
            b"2012-03-31,Cam5,1333195231000000.7,no-change,,,,,\n",
            "line 2: utime '1333195231000000.7' is not a whole number",
        ),
        (
            b"2012-03-31,Cam5,1234567890123456789012345,no-change,,,,,\n",
            "line 2: utime '1234567890123456789012345' is not a whole number",
        ),
        # a blank line and a quoted newline before the bad row: the file's own line is named
        (
            b'\n2012-03-31,Cam5,1333195206000000,no-change,,,,,"two\nlines"\n\n'
            b"2012-03-31,Cam5,1333195207000000,maybe,,,,,\n",
            "line 6: status must be one of",
        ),
        (
            b"2012-03-31,Cam5,1333195206000000,no-change\n",
            "line 2: 4 fields where the header has 9",
        ),
    ],
)
def test_annotation_csv_errors_name_the_file_s_own_line(
    tmp_path: Path, body: bytes, needle: str
) -> None:
    from harness.errors import AnnotationError
    from harness.ingest.annotations import load_annotations

    p = _annotations(tmp_path, body)
    with pytest.raises(AnnotationError) as e:
        load_annotations(p)
    assert needle in str(e.value) and str(p) in str(e.value), str(e.value)


def test_an_unknown_frame_is_named(tmp_path: Path) -> None:
    import pandas as pd

    from harness.errors import AnnotationError
    from harness.ingest.annotations import load_annotations

    p = _annotations(tmp_path, b"2012-03-31,Cam5,1333195299000000,no-change,,,,,\n")
    frames = pd.DataFrame(
        {"session": ["2012-03-31"], "camera": ["Cam5"], "utime": [1333195206000000],
         "width": [120], "height": [160]}
    )  # fmt: skip
    with pytest.raises(AnnotationError) as e:
        load_annotations(p, frames)
    assert "line 2: unknown frame 2012-03-31 Cam5 1333195299000000" in str(e.value)


def test_a_tf_tree_error_is_named_by_inspect_not_called_damage(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``harness inspect`` of a bag whose /tf gives a frame two parents says so (it said 'cannot
    read the whole log ... try --salvage': a broad except turned every error into damage)."""
    assert main(["inspect", str(_two_parents_bag(tmp_path))]) == 1
    err = _err(capsys)
    assert "frame 'c' has two parents in /tf" in err and "--salvage" not in err, err


def _two_parents_bag(tmp_path: Path) -> Path:
    """A ROS2 bag whose /tf holds a -> c and b -> c."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    tm = ts.types["geometry_msgs/msg/TransformStamped"]
    tfm = ts.types["tf2_msgs/msg/TFMessage"]
    hdr = ts.types["std_msgs/msg/Header"]
    stamp = ts.types["builtin_interfaces/msg/Time"]
    tr = ts.types["geometry_msgs/msg/Transform"]
    v3 = ts.types["geometry_msgs/msg/Vector3"]
    q = ts.types["geometry_msgs/msg/Quaternion"]

    def edge(parent: str, child: str) -> object:
        return tm(
            header=hdr(stamp=stamp(sec=1, nanosec=0), frame_id=parent),
            child_frame_id=child,
            transform=tr(
                translation=v3(x=0.0, y=0.0, z=0.0), rotation=q(x=0.0, y=0.0, z=0.0, w=1.0)
            ),
        )

    path = tmp_path / "tfloop"
    with Writer(path, version=8) as w:
        conn = w.add_connection("/tf", tfm.__msgtype__, typestore=ts)
        msg = tfm(transforms=[edge("a", "c"), edge("b", "c")])
        w.write(conn, 1_000_000_000, ts.serialize_cdr(msg, tfm.__msgtype__))
    return path


def test_annotations_export_with_a_frame_table_that_lacks_a_pair_s_reference(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """It was a KeyError traceback; now one line naming the frame, and nothing written."""
    import pandas as pd

    frames = tmp_path / "frames.parquet"
    pd.DataFrame(
        {"session": ["q"], "camera": ["c"], "utime": [1], "image": ["x.png"], "width": [8],
         "height": [8]}
    ).to_parquet(frames)  # fmt: skip
    pairs = tmp_path / "pairs.parquet"
    pd.DataFrame(
        {"q_session": ["q"], "q_camera": ["c"], "q_utime": [1], "r_session": ["map"],
         "r_camera": ["c"], "r_utime": [7]}
    ).to_parquet(pairs)  # fmt: skip
    argv = ["annotations", "export", "--pairs", str(pairs), "--frames", str(frames), "--out",
            str(tmp_path / "t")]  # fmt: skip
    assert main(argv) == 1
    assert "the frame table lacks the reference frame map c 7 of a pair" in _err(capsys)
    assert not (tmp_path / "t").exists()


def test_inspect_of_an_nclt_folder_whose_ground_truth_has_a_non_utf8_byte(
    small_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """It was a UnicodeDecodeError traceback; inspect now counts the rows (the file is bytes to
    it), and ingest names the file and line."""
    import shutil

    from harness.errors import IngestError
    from harness.ingest import ingest_session
    from harness.ingest.config import IngestConfig, SessionConfig

    root = tmp_path / "nclt"
    shutil.copytree(small_world / "nclt", root)
    gt = next((root / "ground_truth").glob("*.csv"))
    raw = gt.read_bytes().splitlines()
    raw[2] = raw[2] + b"\xff"
    gt.write_bytes(b"\n".join(raw) + b"\n")
    assert main(["inspect", str(root)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    session = gt.stem.replace("groundtruth_", "")
    with pytest.raises(IngestError) as e:
        ingest_session(
            SessionConfig(name=session, source=str(root)), IngestConfig(), tmp_path / "o"
        )
    assert str(gt) in str(e.value), str(e.value)

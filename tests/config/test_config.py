"""``harness.config.load``: every value checked (type, range, finiteness, known names) before any
work.

Each case goes through the CLI as a user types it (issue 26, items 2-4): one ``ERROR:`` line that
names the key and the value, exit 1, and no stage run (the output directory stays empty).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from harness.cli import main

from ..conftest import ROOT, one_error

FIXTURE_TOML = ROOT / "datasets" / "fixture.toml"


_err = one_error


def _config(tmp: Path, old: str, new: str, extra: str = "") -> Path:
    text = FIXTURE_TOML.read_text()
    assert old in text, old
    path = tmp / "c.toml"
    path.write_text(text.replace(old, new, 1) + extra)
    return path


CASES = [
    # (replace, with, extra TOML, words the error must hold)
    ("epochs = 6", "epochs = 6\nlr = inf", "", "lr: inf is not a finite number"),
    ("epochs = 6", "epochs = 6\nlr = nan", "", "lr: nan is not a finite number"),
    ('queries = "annotated"', 'queries = "annotated"\nstride_m = inf', "", "stride_m: inf is not"),
    ("bootstrap = 200", "bootstrap = 200", "\n[retrieval]\ngt_radius_m = inf\n", "gt_radius_m"),
    ("bootstrap = 200", "bootstrap = 200", "\n[retrieval]\ndb_stride_m = inf\n", "db_stride_m"),
    ("bootstrap = 200", "bootstrap = 200", "\n[retrieval]\nmemory_mb = nan\n", "memory_mb"),
    ("bootstrap = 200", "bootstrap = 200", "\n[ingest]\nmax_pose_gap_s = inf\n", "max_pose_gap"),
    ("seed = 0", 'seed = "abc"', "", "seed = 'abc': expected an integer"),
    ("seed = 0", "seed = 1.5", "", "seed = 1.5: expected an integer"),
    ("seed = 0", "seed = true", "", "seed = True: expected an integer"),
    ('name = "fixture"', "name = 3", "", "name = 3: expected a non-empty string"),
    ("bootstrap = 200", "bootstrap = 200", "\n[proposals.edges]\nnms_iou = 1.5\n", "nms_iou"),
    ("bootstrap = 200", "bootstrap = 200", "\n[proposals.edges]\nwork_width = 0\n", "work_width"),
    ("bootstrap = 200", "bootstrap = 200", "\n[proposals.edges]\ndilations = []\n", "dilations"),
    ("bootstrap = 200", "bootstrap = 200", "\n[proposals.yolo]\niou = 2.0\n", "yolo] iou"),
    ("loop_scale = 1.5", 'loop_scale = 1.5\nformats = ["nclt", "rosbag9"]', "", "formats"),
    ('name = "autoencoder"', 'name = "netvlad"', "", "[descriptor] name = 'netvlad': unknown"),
    ("bootstrap = 200", "bootstrap = 200", '\n[import]\nscore_kind = "rank"\n', "score_kind"),
    ('name = "autoencoder"', 'name = "autoencoder"\nprefetch = -1', "", "prefetch = -1"),
    ('name = "autoencoder"', 'name = "autoencoder"\nprefetch = 1.5', "", "expected an integer"),
]


@pytest.mark.parametrize(("old", "new", "extra", "words"), CASES)
def test_a_bad_value_is_one_error_before_any_stage(
    tmp_path: Path, capsys: pytest.CaptureFixture, old: str, new: str, extra: str, words: str
) -> None:
    cfg = _config(tmp_path, old, new, extra)
    out = tmp_path / "o"
    fx = tmp_path / "fx"  # never generated: the check comes first
    assert main(["pairs", "--config", str(cfg), "--data-root", str(fx), "--out", str(out)]) == 1
    assert words in _err(capsys)
    assert not (out / "cache").exists() and not fx.exists()


def test_cuda_asked_for_without_cuda(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    cfg = _config(tmp_path, 'name = "autoencoder"', 'name = "autoencoder"\ndevice = "cuda"')
    assert main(["pairs", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 1
    assert "sees no CUDA device" in _err(capsys)


def test_config_files_that_are_not_config_files(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = str(tmp_path / "o")
    assert main(["pairs", "--config", str(tmp_path), "--out", out]) == 1
    assert "config file is a directory, not a file" in _err(capsys)
    latin = tmp_path / "latin.toml"
    latin.write_bytes('name = "caf\xe9"\n'.encode("latin-1"))
    assert main(["pairs", "--config", str(latin), "--out", out]) == 1
    assert "config file is not UTF-8 text" in _err(capsys)
    locked = tmp_path / "locked.toml"
    locked.write_text(FIXTURE_TOML.read_text())
    locked.chmod(0)
    real_read = Path.read_text

    def denied(self: Path, *a: object, **k: object) -> str:
        if self == locked:  # root reads a chmod-000 file; a user does not
            raise PermissionError(13, "Permission denied", str(self))
        return real_read(self, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "read_text", denied)
    assert main(["pairs", "--config", str(locked), "--out", out]) == 1
    err = _err(capsys)
    assert "locked.toml: config file is not readable (permission denied)" in err
    assert "--out" not in err
    os.chmod(locked, 0o644)


def test_a_config_in_a_closed_folder_is_named_not_readable(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A folder closed to the user: the file is not readable, and --out is not the advice."""
    closed = tmp_path / "closed"
    closed.mkdir()
    cfg = closed / "run.toml"
    cfg.write_text(FIXTURE_TOML.read_text())
    real_stat = Path.stat

    def denied(self: Path, *a: object, **k: object) -> os.stat_result:
        if self == cfg:  # root looks into a chmod-000 folder; a user does not
            raise PermissionError(13, "Permission denied", str(self))
        return real_stat(self, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "stat", denied)
    assert main(["pairs", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 1
    err = _err(capsys)
    assert "run.toml: config file is not readable: a folder on its path is closed" in err
    assert "--out" not in err


def test_inputs_named_in_the_config_are_checked_before_ingest(
    tmp_path: Path, capsys: pytest.CaptureFixture, default_world: Path
) -> None:
    """An unknown camera or a missing annotation file: refused before any session is ingested."""
    root = default_world
    cam = _config(
        tmp_path, 'source = "{data_root}/nclt"', 'source = "{data_root}/nclt"\ncamera = "cam5"'
    )
    out = tmp_path / "o"
    assert main(["pairs", "--config", str(cam), "--data-root", str(root), "--out", str(out)]) == 1
    err = _err(capsys)
    assert "camera = 'cam5'" in err and "Cam5" in err and "case-sensitive" in err
    assert not (out / "cache" / "ingest").exists()
    ann = _config(tmp_path, 'annotations = "annotations/fixture.csv"', 'annotations = "nope.csv"')
    assert main(["pairs", "--config", str(ann), "--data-root", str(root), "--out", str(out)]) == 1
    assert "nope.csv: annotation file not found" in _err(capsys)
    assert not (out / "cache" / "ingest").exists()

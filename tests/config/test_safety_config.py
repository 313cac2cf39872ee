"""Flags and config keys are honoured; bad values and bad tables are one ERROR line.

Nothing lost, nothing silently wrong: each case goes through the CLI as a user types it where it
can; bad input gives one ``ERROR:`` line, exit 1, and leaves nothing partial behind.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pandas as pd
import pytest

from harness.cli import main
from harness.config.assemble import load_config
from harness.errors import ConfigError, HarnessError
from harness.pipeline.chain import Pipeline

from ..conftest import ROOT, no_figures
from ..safety_common import FIXTURE_TOML, _config, _err


def test_fusion_methods_are_honoured(local_run: tuple, tmp_path: Path) -> None:
    p, _, _out = local_run
    cfg = dataclasses.replace(
        p.cfg,
        fusion=dataclasses.replace(p.cfg.fusion, methods=("score_max", "rank_fusion", "random")),
    )
    shutil.copytree(_out / "cache", tmp_path / "o" / "cache")  # only fusion and reports rerun
    shutil.copy(_out / ".dbl-harness.json", tmp_path / "o" / ".dbl-harness.json")
    rec = Pipeline(no_figures(cfg), tmp_path / "o").run()
    assert list(rec["table"].index) == [
        "rank_fusion",
        "score_max",
        "random",
    ]  # the method's order, whatever the config's order
    assert pd.read_csv(tmp_path / "o" / "table1.csv")["fusion"].tolist() == [
        "rank_fusion",
        "score_max",
        "random",
    ]
    cols = pd.read_parquet(tmp_path / "o" / "splits" / "roc_max_0.01.parquet").columns
    assert {"loc_rank_fusion", "loc_score_max", "loc_random"} <= set(
        cols
    ) and "loc_score_sum" not in cols


def test_ray_flags_need_the_ray_executor(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
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


def test_an_unreachable_ray_address_is_one_error_line_in_seconds(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """`--executor ray --address HOST:PORT` where nothing listens: ray.init would retry for
    minutes and end in a ConnectionError traceback; the harness says it in one line."""
    import socket

    with socket.socket() as s:  # a port nothing listens on: bound, never listened
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        argv = ["reproduce", "--config", str(FIXTURE_TOML), "--out", str(tmp_path / "o")]
        argv += ["--executor", "ray", "--address", f"ray://127.0.0.1:{port}"]
        assert main(argv) == 1
    err = _err(capsys)
    assert f"cannot reach the Ray cluster at --address ray://127.0.0.1:{port}" in err, err
    assert "refused" in err.lower(), err


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
        # issue 38's and 36's keys
        (None, "\n[fusion]\nrrf_c = -1\n", r"\[fusion\] rrf_c = -1.0 is out of range"),
        (
            ("bootstrap = 200", "bootstrap = 200\nrecall_at = [5, 1]"),
            "",
            r"\[report\] recall_at = \[5, 1\] is out of range; allowed: a non-empty increasing",
        ),
        (
            ("bootstrap = 200", "bootstrap = 200\nrecall_at = [0, 5]"),
            "",
            r"\[report\] recall_at = \[0, 5\] is out of range",
        ),
        (
            ("bootstrap = 200", "bootstrap = 200\ngt_radius_also = 2.0"),
            "",
            r"\[report\] gt_radius_also = 2.0 is out of range; allowed: 0 \(off\) or a second",
        ),
        (None, '\n[detect]\nboxes = "pixels"\n', r"\[detect\] boxes = 'pixels' is out of range"),
        (None, '\n[detect]\nbox_score = "median"\n', r"\[detect\] box_score = 'median'"),
        (None, "\n[detect]\nlocmap_level = 1.0\n", r"\[detect\] locmap_level = 1.0 is out"),
        (None, "\n[detect]\nalarm = 0\n", r"\[detect\] alarm = 0.0 is out of range"),
        (None, "\n[detect]\nlocalization_weight = 0\n", r"\[detect\] localization_weight = 0"),
        (None, "\n[detect]\ncolour = 1\n", r"unknown key"),
        (None, '\n[detect]\ncalibration = "run"\n', r"\[detect\] calibration = 'run' is out"),
        (None, "\n[detect.null]\npairs = 0\n", r"\[detect.null\]: pairs = 0 is out of range"),
        (None, "\n[detect.null]\nshift = 0.5\n", r"\[detect.null\]: shift = 0.5 is out of"),
        (None, '\n[detect.null]\nconstruction = "x"\n', r"construction = 'x' is out of range"),
        (None, "\n[detect.null]\njpeg_quality = 5\n", r"jpeg_quality = 5 is out of range"),
        (None, "\n[detect.null]\ncopies = 3\n", r"\[detect\].null: unknown key"),
        (None, "\n[detect.keypoints]\nratio = 2.0\n", r"ratio = 2.0 is out of range"),
        (None, "\n[proposals.segments]\nk = 1\n", r"\[proposals.segments\] k = 1 is out of range"),
        (
            None,
            "\n[proposals.segments]\nclosings = []\n",
            r"\[proposals.segments\] closings = \[\] is out of range",
        ),
        (
            None,
            "\n[proposals.segments]\nwork_width = 8\n",
            r"\[proposals.segments\] work_width = 8 is out of range",
        ),
        (
            (
                'methods = ["grid5", "edges"]',
                'methods = ["grid5", "edges"]\nreduced_decode = "yes"',
            ),
            "",
            r"reduced_decode",
        ),
        (
            ('methods = ["grid5", "edges"]', 'methods = ["grid5", "edges"]\nthreads = -1'),
            "",
            r"\[proposals\] threads = -1 is out of range",
        ),
        (
            ('name = "autoencoder"', 'name = "autoencoder"\ncrop_threads = -2'),
            "",
            r"\[descriptor\] crop_threads = -2 is out of range",
        ),
    ],
)
def test_bad_config_values_fail_at_load(
    tmp_path: Path, edit: tuple | None, extra: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(_config(tmp_path, edit, extra))


def test_the_new_keys_load_as_typed(tmp_path: Path) -> None:
    """``[fusion] rrf_c``, ``[report] recall_at`` / ``gt_radius_also`` and ``[detect]`` as the
    README writes them."""
    extra = (
        "\n[fusion]\nrrf_c = 30\n"
        '\n[detect]\nboxes = "proposals"\nbox_score = "mean"\nlocmap_level = 0.4\nalarm = 0.05\n'
    )
    edit = ("bootstrap = 200", "bootstrap = 200\nrecall_at = [1, 3]\ngt_radius_also = 5")
    cfg = load_config(_config(tmp_path, edit, extra))
    assert cfg.fusion.rrf_c == 30.0
    assert cfg.report.recall_at == (1, 3) and cfg.report.gt_radius_also == 5.0
    d = cfg.detect
    assert (d.boxes, d.box_score, d.locmap_level, d.alarm) == ("proposals", "mean", 0.4, 0.05)
    # the nested tables are their options, not plain tables
    cfg = load_config(_config(tmp_path, None, '\n[detect.null]\npairs = 200\nconstruction = '
                              '"perturbed"\n\n[detect.keypoints]\nratio = 0.7\n'))  # fmt: skip
    assert (cfg.detect.null.pairs, cfg.detect.null.construction) == (200, "perturbed")
    assert cfg.detect.keypoints.ratio == 0.7 and cfg.detect.calibration == "null"


def test_bad_config_is_one_error_line_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    cfg = _config(tmp_path, ("bootstrap = 200", "bootstrap = 200\nci = 1.5"))
    assert main(["reproduce", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 1
    assert "ci = 1.5" in _err(capsys) and not (tmp_path / "o").exists()


def test_annotations_without_a_change_frame_are_an_error(
    default_world: Path, tmp_path: Path
) -> None:
    ann = pd.read_csv(ROOT / "annotations" / "fixture.csv")
    ann = ann[ann["status"] == "no-change"]
    ann.to_csv(tmp_path / "nochange.csv", index=False)
    cfg = load_config(FIXTURE_TOML, data_root=str(default_world))
    cfg = dataclasses.replace(cfg, annotations=tmp_path / "nochange.csv")
    with pytest.raises(HarnessError, match="no frame is annotated 'change'"):
        Pipeline(cfg, tmp_path / "o").run()


def test_imported_ranks_with_foreign_ids_are_an_error(
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
                "proposal_method": r.proposal_method,
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

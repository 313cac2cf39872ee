"""``python -m bench.detect_choice`` and ``python -m bench.alarms`` as docs/decisions.md types
them, on the real pairs.

The whole choice runs every candidate on three sets (about 25 minutes); here one candidate, not
the default (``tests/detect/test_detect_real.py`` holds the default's row on the same pairs to
``docs/decisions.md``), on ``../shared/realdata/obchange-dev`` (skipped where the folder is absent),
through to its last output: the table of candidates, the rule's pick among them, and the run's
``detect.json`` with the flags as typed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ..conftest import ROOT, shared_stages
from .test_detect_real import OBCHANGE_DEFAULT

REAL = ROOT.parent / "shared" / "realdata" / "obchange-dev"


def test_a_bad_candidate_is_one_error_line(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "bench.detect_choice", "--sets", "obchange-dev", "--candidates",
         "keypoints/grid5/area", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert proc.returncode == 1 and proc.stderr.startswith("ERROR: --candidates keypoints/grid5")


@pytest.mark.skipif(not REAL.is_dir(), reason=f"no real pairs here: {REAL} is absent")
def test_the_choice_runs_as_typed_on_the_real_pairs(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    cands = "keypoints/selective/difference_product/ratio-fallback-novelty-w4"  # the default's
    run = tmp_path / "obchange-dev" / cands.replace("/", "-")
    with shared_stages(tmp_path_factory, OBCHANGE_DEFAULT, run):  # its stages, computed once
        proc = subprocess.run(
            [sys.executable, "-m", "bench.detect_choice", "--sets", "obchange-dev",
             "--candidates", cands, "--out", str(tmp_path)],
            cwd=ROOT, capture_output=True, text=True, check=True,
        )  # fmt: skip
    md = (tmp_path / "detect_choice.md").read_text()
    assert "| keypoints | selective | difference_product | ratio-fallback-novelty-w4 | " in md
    assert "| none | selective | plain difference | ratio-fallback-novelty-w4 | " in md  # Table D's
    # the development rooms decide (docs/decisions.md, *Choosing the default*): not run here
    assert "Chosen by the rule: none (obchange-rooms was not run)" in md and md in proc.stdout
    rec = json.loads((tmp_path / "obchange-dev" / "keypoints-selective-difference_product-"
                      "ratio-fallback-novelty-w4" / "detect.json").read_text())  # fmt: skip
    opt = rec["options"]  # --localizer, --proposals, --box-prior and the settings reached the run
    assert (opt["localizer"], opt["proposals"], opt["box_prior"], opt["not_comparable"]) == (
        "keypoints", "selective", "difference_product", "fallback")  # fmt: skip
    assert (opt["difference"]["box_score"], opt["difference"]["ring"]) == ("ratio", 0.25)
    assert opt["difference"]["colour"] == "novelty" and opt["localization_weight"] == 4
    rows = json.loads((tmp_path / "detect_choice.json").read_text())
    assert all(0 <= r["chance_high"] < 1 and r["recall"] > 0 for r in rows)


@pytest.mark.skipif(not REAL.is_dir(), reason=f"no real pairs here: {REAL} is absent")
def test_the_alarms_measurement_runs_as_typed_on_the_real_pairs(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """``python -m bench.alarms --sets obchange-dev`` as docs/decisions.md types it (*Calibrated
    alarms*): both calibrations, the null's flags of the revisited frames with their exact
    interval, the old calibration's beside them. The default detector's stages on these pairs
    are computed once a test session (the set's run directory seeded with them)."""
    with shared_stages(tmp_path_factory, OBCHANGE_DEFAULT, tmp_path / "obchange-dev"):
        proc = subprocess.run(
            [sys.executable, "-m", "bench.alarms", "--sets", "obchange-dev", "--out",
             str(tmp_path)], cwd=ROOT, capture_output=True, text=True, check=True,
        )  # fmt: skip
    md = (tmp_path / "alarms.md").read_text()
    assert md in proc.stdout
    rows = {r["calibration"]: r for r in json.loads((tmp_path / "alarms.json").read_text())}
    assert set(rows) == {"null", "within-run"}
    null = rows["null"]["null"]
    assert (null["construction"], null["pairs"]) == ("perturbed", 100)
    assert rows["within-run"]["null"] == {"method": "within-run"}
    for r in rows.values():
        assert r["changed_frames"] == 10 and "alarm_measured" not in r  # none annotated no-change
        k = round(r["alarm_detected"] * 10)
        assert f"| {k} of 10: {r['alarm_detected']:.3f} [" in md

"""``harness detect`` on real revisits nobody here made (issue 63): ``../shared/realdata``.

The images are read where they lie and never enter the repository (their licence is unverified:
read the folder's README). Where the folder is absent the tests skip, saying so.
"""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

from harness.cli import main

from ..conftest import ROOT

REAL = ROOT.parent / "shared" / "realdata" / "obchange-dev"
pytestmark = pytest.mark.skipif(
    not (REAL / "annotations.csv").is_file(),
    reason=f"no real pairs here: {REAL} is absent (shared/realdata is read, never committed)",
)


@pytest.fixture(scope="module")
def real_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """The default command on the ten real revisits, as a user types it."""
    out = tmp_path_factory.mktemp("obchange") / "run"
    argv = ["detect", "--map-images", str(REAL / "A"), "--query-images", str(REAL / "B"),
            "--annotations", str(REAL / "annotations.csv"), "--out", str(out)]  # fmt: skip
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    return out, buf.getvalue()


def test_the_default_detector_finds_real_changes_above_its_chance_band(
    real_run: tuple[Path, str],
) -> None:
    """Table D's detector row against its chance band and the baselines, as docs/method.md quotes
    it (*Keypoint localization*): above the band's top and above the aligned difference, box area
    and cover count; its verdict is the rule's (10 frames: a wide interval)."""
    out, printed = real_run
    t = pd.read_csv(out / "tableD.csv").set_index("row")
    det = t.loc["detector"]
    assert det["ap50_voc_all_point"] > det["chance_high"], det
    for row in ("aligned difference (pixels, no localizer)", "box area alone (no pixel)",
                "cover count alone (no pixel)"):  # fmt: skip
        assert det["ap50_voc_all_point"] > t.loc[row, "ap50_voc_all_point"], row
    quoted = (ROOT / "docs" / "method.md").read_text()
    m = re.search(r"`harness detect` with no flags on `obchange-dev`: AP50 (\d\.\d{3})", quoted)
    assert m is not None, "docs/method.md quotes the default's AP50 on obchange-dev"
    assert abs(det["ap50_voc_all_point"] - float(m.group(1))) <= 0.002, (det, m.group(1))
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert (
        f"the same default reaches AP50 {det['ap50_voc_all_point']:.3f} against a chance band up "
        f"to {det['chance_high']:.3f}"
    ) in readme
    assert "Table D" in printed


def test_the_page_and_alignment_name_the_users_files(real_run: tuple[Path, str]) -> None:
    """The page reads "B against the map A", its gallery names the files, "When" says the frames
    were paired by name, and ``alignment.csv`` names both images of each pair."""
    out, _ = real_run
    page = (out / "detect.html").read_text()
    assert "What changed: B against the map A" in page
    assert "query Office_02.jpg" in page and "query query" not in page
    assert "paired with the map image of the same file name" in page
    assert "retrieves best" not in page
    al = pd.read_csv(out / "alignment.csv")
    assert set(al["q_image"]) == {p.name for p in (REAL / "B").iterdir()}
    assert (al["q_image"] == al["r_image"]).all()

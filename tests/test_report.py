"""``report.html``: written by every run and by ``harness report OUT``, rendered in a real browser
(headless Chromium): every image loads, every table is there, and a screenshot is taken."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from harness.cli import main

SECTIONS = (
    "facts",
    "localization",
    "tableI",
    "tableS",
    "tableP",
    "comparisons",
    "pr",
    "heatmap",
    "gallery",
)
TABLES = ("facts", "localization", "I", "S", "P", "cmpI", "cmpS", "cmpP", "heatmap")


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip(
        "no Chromium here: install Debian's chromium package (apt-get install chromium); "
        ".ci/run installs it where it can"
    )


def test_every_run_writes_the_report_in_order(local_run: tuple) -> None:
    _, rec, out = local_run
    page = (out / "report.html").read_text()
    assert rec["report_html"] == str(out / "report.html")
    positions = [page.index(f'id="{s}"') for s in SECTIONS]
    assert positions == sorted(positions)
    for t in TABLES:
        assert f'data-table="{t}"' in page, t
    assert (
        "WARNING (Table I)" in page and "http://" not in page and "https://" not in page
    )  # nothing fetched at view time
    thumbs = sorted((out / "report").glob("*.jpg"))
    assert (
        len(thumbs) == 6 * 2 * 3
    )  # six methods x (false positives, missed changes) x [report] gallery = 3
    for t in thumbs:
        assert f'src="report/{t.name}"' in page
    assert re.search(r"roc_max_0\.05\.parquet</a> row \d+", page)
    assert (out / "report.html").stat().st_size < 200_000 and sum(
        t.stat().st_size for t in thumbs
    ) < 2_000_000


def test_harness_report_rebuilds_the_page_with_a_smaller_gallery(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    _, _, out = local_run
    shutil.copytree(out, tmp_path / "o")
    assert main(["report", str(tmp_path / "o"), "--gallery", "1"]) == 0
    assert f"report: {tmp_path / 'o' / 'report.html'}" in capsys.readouterr().out
    assert (
        len(list((tmp_path / "o" / "report").glob("*.jpg"))) == 6 * 2
    )  # the earlier page's extra thumbnails are gone
    assert main(["report", str(tmp_path / "nothing")]) == 1
    assert "no run.json here" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "o"), "--gallery", "-1"]) == 1


def test_the_page_renders_in_a_real_browser(local_run: tuple, tmp_path: Path) -> None:
    chromium = _chromium()
    _, _, out = local_run
    url = (out / "report.html").resolve().as_uri()
    flags = [
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        "--virtual-time-budget=15000",
    ]
    dom = subprocess.run(
        [chromium, *flags, "--dump-dom", url],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    body = re.search(r"<body([^>]*)>", dom)
    assert body, dom[:500]
    attrs = dict(re.findall(r'data-([a-z-]+)="([^"]*)"', body.group(1)))
    assert int(attrs["images-total"]) >= 36 + 5  # thumbnails and PR curves
    assert attrs["images-loaded"] == attrs["images-total"], attrs  # every image loads
    assert int(attrs["tables"]) >= len(TABLES)
    shot = tmp_path / "report.png"
    subprocess.run(
        [chromium, *flags, "--window-size=1280,2200", f"--screenshot={shot}", url],
        capture_output=True,
        timeout=120,
        check=True,
    )
    import numpy as np
    from PIL import Image

    with Image.open(shot) as im:
        assert im.size == (1280, 2200)
        grey = np.asarray(im.convert("L"))
    assert (grey < 100).mean() > 0.005 and (
        grey > 240
    ).mean() > 0.3  # text on a light page, not a blank or an error page

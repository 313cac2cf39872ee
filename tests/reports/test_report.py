"""``report.html``: written by every run and by ``harness report OUT``, rendered in a real browser
(headless Chromium): every image loads, every table is there, and a screenshot is taken."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from harness.cli import main

#: The fair comparison first; the paper's protocol (Table I, its figures) last.
SECTIONS = (
    "facts",
    "localization",
    "tableS",
    "tableP",
    "comparisons",
    "pr",
    "heatmap",
    "gallery",
    "protocol",
    "tableI",
    "prI",
    "heatmapI",
    "galleryI",
)
TABLES = ("facts", "localization", "S", "P", "cmpS", "cmpP", "cmpI", "heatmap", "I", "heatmapI")


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
    assert page.index('data-legend="floor"') < page.index('id="tableS"')
    assert page.index('id="protocol"') < page.index("WARNING (Table I)") < page.index('id="tableI"')
    thumbs = sorted((out / "report").glob("*.jpg"))
    # six methods x (false positives, missed changes) x [report] gallery = 3 under Table S's
    # labels, and x 1 under Table I's (collapsed at the end of the page)
    assert len(thumbs) == 6 * 2 * 3 + 6 * 2 * 1
    assert sorted((out / "report").glob("pr_*.png")) == [
        out / "report" / "pr_I.png",
        out / "report" / "pr_S.png",
    ]
    assert "(stratum SoB [" in page
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
        len(list((tmp_path / "o" / "report").glob("*.jpg"))) == 6 * 2 * 2
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
    assert int(attrs["images-total"]) >= 48 + 2  # thumbnails and the two PR figures
    assert attrs["images-loaded"] == attrs["images-total"], attrs  # every image loads
    assert int(attrs["tables"]) >= len(TABLES)
    # the order a reader meets: the legend and the fair tables before the paper's protocol
    order = [
        dom.index(k)
        for k in (
            'data-legend="floor"',
            'id="tableS"',
            'id="tableP"',
            'id="comparisons"',
            'id="protocol"',
            'id="tableI"',
        )
    ]
    assert order == sorted(order)
    assert re.search(r"<details>\s*<summary>Table I", dom)  # collapsed by default
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


def test_a_corridor_run_shows_table_s_green_and_table_i_last(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """A hand-made run directory like a real corridor's: Table I at 1.00 everywhere, Table S modest
    (0.26 against a floor of 0.12 and a band to 0.15, clear of random), one method that cannot be
    told from chance, one below it; every verdict written by §9's rule, as the harness does."""
    import pandas as pd

    from harness.evaluate.chance import verdict

    _, _, run = local_run
    out = tmp_path / "corridor"
    shutil.copytree(run, out)
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    main_rows = (summ["proposal_method"] == "all") & (summ["season_pair"] == "all")
    t1 = main_rows & (summ["table"] == "I")
    summ.loc[t1, ["ap", "ci_low", "ci_high"]] = 1.0
    ts = main_rows & (summ["table"] == "S")
    summ.loc[ts, ["floor", "chance_low", "chance_high", "positive_rate"]] = (0.12, 0.09, 0.15, 0.07)
    for method, (ap, lo, hi, dlo, dhi) in {
        "rank_fusion": (0.26, 0.18, 0.33, 0.08, 0.25),
        "score_max": (0.13, 0.07, 0.21, -0.05, 0.12),
        "size_prior": (0.05, 0.02, 0.08, -0.16, -0.02),
        "random": (0.12, 0.08, 0.17, 0.0, 0.0),
    }.items():
        sel = ts & (summ["fusion"] == method)
        summ.loc[sel, ["ap", "ci_low", "ci_high", "vs_random_diff_ci_low"]] = (ap, lo, hi, dlo)
        summ.loc[sel, "vs_random_diff_ci_high"] = dhi
        summ.loc[sel, "verdict"] = verdict(ap, 0.09, 0.15, dlo, dhi)
    summ.to_parquet(out / "splits" / "summary.parquet")
    assert main(["report", str(out)]) == 0
    page = (out / "report.html").read_text()
    s_start, s_end = page.index('id="tableS"'), page.index('id="tableP"')
    table_s = page[s_start:s_end]

    def verdicts(block: str, label: str) -> set[str]:
        row = block[block.index(f"<td>{label}</td>") :].split("</tr>")[0]
        return set(re.findall(r'data-verdict="([a-z]+)"', row))

    assert verdicts(table_s, "rank fusion") == {"above"}  # 0.26 over the band, clear: green
    assert verdicts(table_s, "score max") == {"chance"}  # inside the band: grey
    assert verdicts(table_s, "size prior (no pixel)") == {"below"}  # under it, clear: red
    assert verdicts(table_s, "random") == {"chance"}  # chance by construction, never green
    # Table I at 1.00 comes after every fair table, in the protocol section, collapsed
    assert page.index('id="tableI"') > page.index('id="protocol"') > s_end
    assert page.index('id="protocol"') > page.index('id="gallery"')


def test_every_colour_of_the_fixture_page_is_the_rule_recomputed_from_the_summary(
    local_run: tuple,
) -> None:
    """method §9: each AP cell's verdict on the page (Tables I, S and P) is
    :func:`harness.evaluate.chance.verdict` of its row in ``splits/summary.parquet``; the random
    baseline is never above chance, and no baseline is above chance in Tables S and P."""
    import html

    import pandas as pd

    from harness.evaluate.chance import verdict
    from harness.methods import METHOD_LABELS
    from harness.reports.change import pivot

    _, rec, out = local_run
    page = (out / "report.html").read_text()
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    summ = summ[summ["localizer"] == summ["localizer"].iloc[0]]
    methods = rec["reports"].methods
    checked = 0
    for table in ("I", "S", "P"):
        block = page[page.index(f'<table data-table="{table}">') :].split("</table>")[0]
        piv = {
            v: pivot(summ, table, methods, v)
            for v in ("ap", "chance_low", "chance_high", "vs_random_diff_ci_low")
        }
        hi = pivot(summ, table, methods, "vs_random_diff_ci_high")
        for m in methods:
            label = html.escape(METHOD_LABELS[m])
            row = block[block.index(f"<td>{label}</td>") :].split("</tr>")[0]
            shown = re.findall(r'data-verdict="([a-z]+)"', row)
            want = [
                verdict(*(piv[v].loc[m, c] for v in piv), hi.loc[m, c]) for c in piv["ap"].columns
            ]
            assert shown == want, (table, m, shown, want)
            checked += len(shown)
            if m == "random" or (table != "I" and m in ("size_prior", "cover_count")):
                assert "above" not in shown, (table, m, shown)
    assert checked == len(methods) * (5 + 5 + 2)

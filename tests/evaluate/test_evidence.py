"""method §9, *evidence before a verdict* (issue 50): one positive earns no ▲, in any renderer.

The issue's run: real frames with one annotated change box printed Table I ``1.00 [1.00, 1.00] ▲``
for rank fusion, ``size_prior`` and ``cover_count``, Table S and P ``0.00 ▲``: green cells from
one positive. Here the fixture's annotations keep one change box and mark every other annotated
frame ``no-change`` (the same annotated frames, so the same pairs, model and ranks: the run reuses
the fixture run's stages), and ``harness reproduce`` runs as a user types it.
"""

from __future__ import annotations

import contextlib
import io
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.cli import main
from harness.evaluate import chance

from ..conftest import ROOT, seed_cache

MARKS = ("▲", "▼")


def test_too_few_positive_images_for_the_bootstrap_to_vary_gives_no_verdict() -> None:
    above = (0.9, 0.0, 0.2, 0.1, 0.5)  # AP far above the band, paired difference clear of 0
    assert chance.verdict(*above) == "above"
    assert chance.verdict(*above, chance.Evidence(5)) == "above"
    assert chance.verdict(*above, chance.Evidence(4)) == "few"
    assert chance.verdict(*above, chance.Evidence(2, needed=1)) == "above"
    # one positive image: every resample holding it holds the same positives, whatever `needed`
    assert chance.verdict(*above, chance.Evidence(1, needed=1)) == "few"
    below = (0.01, 0.1, 0.2, -0.5, -0.1)
    assert chance.verdict(*below, chance.Evidence(2)) == "few"
    # no positive at all stays undefined (NaN AP), never "few"
    assert chance.verdict(float("nan"), 0.0, 0.2, 0.1, 0.5, chance.Evidence(0)) == "undefined"
    assert chance.few_text(3) == "too few positives (3)"


def _one_box(src: Path, dst: Path) -> int:
    """The annotations with one change box left (the largest); every other annotated frame
    ``no-change``."""
    ann = pd.read_csv(src)
    key = ["session", "camera", "utime"]
    change = ann[ann["status"] == "change"]
    area = (change["x2"] - change["x1"]) * (change["y2"] - change["y1"])
    keep = change.loc[[area.idxmax()]]  # the largest: the one most proposals fit inside
    others = ann.drop_duplicates(key).merge(keep[key], on=key, how="left", indicator=True)
    others = others[others["_merge"] == "left_only"].drop(columns="_merge")
    others = others.assign(status="no-change", x1=np.nan, y1=np.nan, x2=np.nan, y2=np.nan, label="")
    pd.concat([keep, others], ignore_index=True).to_csv(dst, index=False)
    return int(ann.drop_duplicates(key).shape[0])


@pytest.fixture(scope="module")
def one_positive(local_run: tuple, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """``harness reproduce`` with one annotated change box: (out, what it printed)."""
    p, _, run = local_run
    base = tmp_path_factory.mktemp("one-positive")
    frames = _one_box(ROOT / "annotations" / "fixture.csv", base / "one.csv")
    cfg = (ROOT / "datasets" / "fixture.toml").read_text()
    cfg = cfg.replace(
        'annotations = "annotations/fixture.csv"', f'annotations = "{base / "one.csv"}"'
    ).replace('"datasets/models"', f'"{ROOT}/datasets/models"')
    (base / "one.toml").write_text(cfg)
    out = base / "out"
    seed_cache(run, out)  # the same frames, pairs, proposals, model and ranks
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["reproduce", "--config", str(base / "one.toml"),
                     "--data-root", str(p.cfg.data_root), "--out", str(out)])  # fmt: skip
    assert code == 0
    assert frames == _one_box(ROOT / "annotations" / "fixture.csv", base / "again.csv")
    return out, buf.getvalue()


def test_one_positive_prints_no_verdict_in_any_renderer(one_positive: tuple[Path, str]) -> None:
    out, printed = one_positive
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    pooled = summ[(summ["proposal_method"] == "all") & (summ["season_pair"] == "all")]
    assert pooled["positive_images"].max() <= 1
    assert set(pooled["verdict"]) <= {"few", "undefined"}, set(pooled["verdict"])
    assert (pooled["positive_images_needed"] == 5).all()
    texts = {
        "console": printed,
        **{f: (out / f).read_text() for f in ("table1.md", "tableS.md", "tableP.md")},
        **{f: (out / f).read_text() for f in ("table1.tex", "tableS.tex", "tableP.tex")},
    }
    for name, text in texts.items():
        # the rows of the tables (the legend under each names the marks it explains)
        rows = [x for x in text.splitlines() if x.startswith("|") or "│" in x or " & " in x]
        assert rows, name
        assert not any(m in x for x in rows for m in MARKS), name
        assert any("too few positives (1)" in x for x in rows), name
    for name in ("table1.md", "tableS.md", "tableP.md"):
        warnings = [x for x in texts[name].splitlines() if "too few positives (n)" in x]
        assert len(warnings) == 1, name  # one line under the table says why
    assert "blacktriangle" not in texts["table1.tex"]
    page = (out / "report.html").read_text()
    assert not re.search(r'data-verdict="(above|below)"', page)
    assert 'data-verdict="few"' in page and "too few positives (1)" in page
    few_cells = re.findall(r'<td data-verdict="few" style="background:([^"]+)"', page)
    assert few_cells and set(few_cells) == {"#ffffff"}  # no colour


def test_the_threshold_is_a_config_key(one_positive: tuple[Path, str], tmp_path: Path) -> None:
    """``[report] min_positive_images`` is read from the config; a bad value is one error naming
    the key."""
    out, _ = one_positive
    cfg = (
        (out.parent / "one.toml")
        .read_text()
        .replace("[report]\n", "[report]\nmin_positive_images = 0\n")
    )
    (tmp_path / "bad.toml").write_text(cfg)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["reproduce", "--config", str(tmp_path / "bad.toml"), "--out",
                     str(tmp_path / "o")]) == 1  # fmt: skip
    assert "[report] min_positive_images" in err.getvalue()
    assert len(err.getvalue().strip().splitlines()) == 1


def test_the_fixture_keeps_its_verdicts(local_run: tuple) -> None:
    """With the fixture's 27 change boxes the pooled rows rest on enough positive images."""
    _, _, out = local_run
    summ = pd.read_parquet(out / "splits" / "summary.parquet")
    pooled = summ[(summ["proposal_method"] == "all") & (summ["season_pair"] == "all")]
    s = pooled[(pooled["table"] == "S") & (pooled["fusion"] == "rank_fusion")]
    assert (s["positive_images"] >= 5).all() and "few" not in set(s["verdict"])
    assert "▲" in (out / "tableS.md").read_text()


def test_table_d_uses_the_same_rule(tmp_path: Path) -> None:
    """Table D's rows get ``few`` with one annotated change frame, whatever their AP."""
    from harness.evaluate.table_d_chance import table_d_chance

    box = np.array([[10.0, 10.0, 30.0, 30.0]])
    gts = {0: box, 1: np.zeros((0, 4)), 2: np.zeros((0, 4))}
    cands = {0: box, 1: box + 40, 2: box + 80}
    dets = {
        "detector": {0: (box, np.array([1.0])), 1: (box + 40, np.array([0.1]))},
        "random": {0: (box, np.array([0.2])), 1: (box + 40, np.array([0.9]))},
    }
    res = table_d_chance(
        cands, gts, dets, lambda b, s: np.argsort(-s), chance.ChanceSettings(200, 200, 0.95, 0)
    )
    assert res["detector"]["ap50"] == 1.0
    assert res["detector"]["verdict"] == "few" and res["detector"]["positive_images"] == 1


def test_harness_report_rewrites_the_page_with_the_same_rule(
    one_positive: tuple[Path, str], tmp_path: Path
) -> None:
    """``harness report OUT`` re-renders the page from the run's files: the same "too few"."""
    out, _ = one_positive
    shutil.copytree(out, tmp_path / "copy")
    (tmp_path / "copy" / "report.html").unlink()
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["report", str(tmp_path / "copy")]) == 0
    page = (tmp_path / "copy" / "report.html").read_text()
    assert "too few positives (1)" in page
    assert not re.search(r'data-verdict="(above|below)"', page)

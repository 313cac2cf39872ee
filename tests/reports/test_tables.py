"""Tables a reviewer can trust (method §7-10): stratified AP, pixel and image AP, paired
comparisons, confound warnings and LaTeX, by hand and on the fixture run."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.evaluate.metrics import (
    average_precision,
    bootstrap_aps,
    paired_difference,
    resample_counts,
    stratified_ap,
    weighted_average_precision,
)
from harness.evaluate.pixel_aps import pixel_regions
from harness.evaluate.verdicts import confound_warnings
from harness.reports.render import table_latex

EDGES = [0.0, 0.1, 0.5, 1.0]


def test_stratified_ap_by_hand() -> None:
    """Stratum [0, 0.1): + (0.9), - (0.8), + (0.1): AP = (51 * 1 + 50 * 2/3) / 101, rate 2/3.
    Stratum [0.1, 0.5): + (0.2), - (0.7): AP = 1/2 (all 101 points at precision 1/2), rate 1/2.
    Stratum [0.5, 1]: negatives only: no part. Weighted by positives 2 and 1."""
    y = np.array([1, 0, 1, 1, 0, 0, 0], bool)
    s = np.array([0.9, 0.8, 0.1, 0.2, 0.7, 0.95, 0.99])
    sob = np.array([0.05, 0.05, 0.05, 0.3, 0.3, 0.7, 1.0])  # 1.0 belongs to the closed last stratum
    ap1, ap2 = (51 + 50 * 2 / 3) / 101, 0.5
    ap, floor = stratified_ap(y, s, sob, EDGES)
    assert ap == pytest.approx((2 * ap1 + 1 * ap2) / 3)
    assert floor == pytest.approx((2 * 2 / 3 + 1 * 1 / 2) / 3)


def test_stratified_ap_stratum_without_negative_or_positive() -> None:
    y = np.array([1, 1, 0, 1, 0], bool)
    s = np.array([0.5, 0.4, 0.3, 0.9, 0.1])
    sob = np.array(
        [0.01, 0.02, 0.6, 0.2, 0.2]
    )  # [0, 0.1): positives only; [0.5, 1]: a negative only
    ap, floor = stratified_ap(y, s, sob, EDGES)
    assert ap == pytest.approx(1.0) and floor == pytest.approx(
        0.5
    )  # only [0.1, 0.5) counts: + 0.9 above - 0.1
    assert np.isnan(
        stratified_ap(y[:2], s[:2], sob[:2], EDGES)[0]
    )  # no stratum has both: NaN, never 0 or 1


def test_stratified_ap_ties_across_strata_do_not_interact() -> None:
    """Equal scores in different strata never share a PR point: each stratum is ranked alone.
    Pooled, the tie at 0.5 would enter together (AP 2/3); stratified, each stratum is 1.0 or 0.5."""
    y = np.array([1, 0, 1, 0], bool)
    s = np.array([0.5, 0.5, 0.5, 0.4])
    sob = np.array([0.05, 0.3, 0.3, 0.05])
    # [0, 0.1): + 0.5 above - 0.4: AP 1, rate 1/2; [0.1, 0.5): + and - tied at 0.5: AP 1/2, rate 1/2
    ap, floor = stratified_ap(y, s, sob, EDGES)
    assert ap == pytest.approx(0.75) and floor == pytest.approx(0.5)
    assert average_precision(y, s) == pytest.approx(2 / 3)


def test_weighted_ap_equals_repetition() -> None:
    rng = np.random.default_rng(0)
    y = rng.random(40) < 0.3
    s = np.round(rng.random(40), 1)
    w = rng.integers(0, 4, 40)
    rep = np.repeat(np.arange(40), w)
    assert weighted_average_precision(y, s, w) == pytest.approx(average_precision(y[rep], s[rep]))


def test_pixel_ap_on_a_4x4_image_by_hand() -> None:
    """Boxes A = [0,2]x[0,2] (LoC 0.9) and B = [0,4]x[0,4] (LoC 0.2); change box [0,1]x[0,2].
    Pixels: A's 4 take 0.9 (2 changed), B's other 12 take 0.2 (none changed). Ranking: 0.9 first
    (precision 2/4, recall 1), so every R gets precision 1/2: pixel AP = 0.5."""
    boxes = np.array([[0, 0, 2, 2], [0, 0, 4, 4]], float)
    loc = np.array([0.9, 0.2])
    area, pos, owner = pixel_regions(boxes, np.array([[0, 0, 1, 2]], float), 4, 4)
    assert area.sum() == 16 and area[pos].sum() == 2
    scores = loc[owner]
    assert area[scores == 0.9].sum() == 4 and area[scores == 0.2].sum() == 12
    assert weighted_average_precision(pos, scores, area) == pytest.approx(0.5)
    # the same by brute force over the 16 pixel centres
    px = [(u + 0.5, v + 0.5) for v in range(4) for u in range(4)]
    lab = [u < 1 and v < 2 for u, v in px]
    sc = [0.9 if (u < 2 and v < 2) else 0.2 for u, v in px]
    assert average_precision(lab, sc) == pytest.approx(0.5)
    # a region no box holds has owner -1 (the caller gives it the method's lowest LoC)
    _, _, own = pixel_regions(boxes[:1], np.zeros((0, 4)), 4, 4)
    assert (own == -1).sum() == 3


def test_paired_bootstrap_difference_and_sign_flips() -> None:
    rng = np.random.default_rng(1)
    y = rng.random(300) < 0.3
    g = np.repeat(np.arange(30), 10)
    good = y + rng.normal(0, 0.5, 300)
    bad = y + rng.normal(0, 3.0, 300)
    c = resample_counts(30, 200, 0)
    a, b = bootstrap_aps(y, good, g, c), bootstrap_aps(y, bad, g, c)
    d = paired_difference(a, b, average_precision(y, good), average_precision(y, bad), 0.95)
    assert d["diff"] > 0 and d["diff_ci_low"] > 0 and d["sign_flip_share"] < 0.05
    same = paired_difference(a, a, 0.5, 0.5, 0.95)
    assert same["diff"] == 0 and same["diff_ci_low"] == same["diff_ci_high"] == 0


def _main(rows: list[tuple[str, str, float]]) -> pd.DataFrame:
    return pd.DataFrame(
        [{"split": sp, "roc_max": float(sp), "fusion": m, "ap": ap} for sp, m, ap in rows]
    )


def test_confound_warning_triggered_and_not() -> None:
    rows = [
        ("0.01", "rank_fusion", 0.80),
        ("0.01", "score_max", 0.90),
        ("0.01", "size_prior", 0.89),
        ("0.01", "random", 0.10),
        ("0.05", "rank_fusion", 0.80),
        ("0.05", "score_max", 0.90),
        ("0.05", "size_prior", 0.70),
        ("0.05", "random", 0.10),
    ]
    w = confound_warnings(_main(rows), "Table I")
    assert len(w) == 1
    assert (
        "size_prior" in w[0]
        and "RoC-max 0.01: 0.89 vs score_max 0.90" in w[0]
        and "0.05" not in w[0]
        and "Table S" in w[0]
    )
    rows[2] = ("0.01", "size_prior", 0.87)  # 0.03 below the best: no warning
    assert confound_warnings(_main(rows), "Table I") == []


def test_latex_table_parses_back() -> None:
    t = pd.DataFrame(
        {0.01: [0.74, 0.69, np.nan, 1.0], 0.05: [0.72, 0.68, 0.5, 0.99]},
        index=["rank_fusion", "rank_no_fusion", "rank_fusion_asc", "size_prior"],
    )
    tex = table_latex(t)
    assert tex.startswith(r"\begin{tabular}{lrr}") and r"\toprule" in tex and r"\bottomrule" in tex
    body = tex.split(r"\midrule", 1)[1].split(r"\bottomrule")[0]
    rows = [
        r.strip().removesuffix(r"\\").strip()
        for r in body.splitlines()
        if r.strip() and r.strip() != r"\midrule"
    ]
    assert (
        len(rows) == 4 and tex.count(r"\midrule") == 2
    )  # header rule, then the rule before the variants and baselines
    parsed = [[c.strip() for c in r.split(" & ")] for r in rows]
    assert parsed[0] == ["rank fusion", "0.74", "0.72"] and parsed[1] == [
        "rank w/o fusion",
        "0.69",
        "0.68",
    ]
    assert parsed[2][1] == "--" and parsed[3][0] == "size prior (no pixel)"
    for (_m, row), p in zip(t.iterrows(), parsed, strict=True):
        vals = [float("nan") if c == "--" else float(c) for c in p[1:]]
        np.testing.assert_allclose(vals, row.to_numpy(), atol=0.005)
    # a label with LaTeX's special characters is escaped (a user's method or localizer name)
    odd = pd.DataFrame({"0.01": [0.5]}, index=["a & b_1 %"])
    assert r"a \& b\_1 \%" in table_latex(odd)


# ------------------------------------------------------------------ on the fixture run


def test_fixture_writes_tables_s_and_p_with_intervals_and_comparisons(local_run: tuple) -> None:
    _, rec, out = local_run
    s = pd.read_parquet(out / "splits" / "summary.parquet")
    pooled = s[(s["proposal_method"] == "all") & (s["season_pair"] == "all")]
    assert set(pooled["table"]) == {"I", "S", "P"}
    for table in ("I", "S", "P"):
        t = pooled[pooled["table"] == table]
        rf = t[t["fusion"] == "rank_fusion"]
        assert (rf["ci_low"] <= rf["ap"] + 1e-9).all() and (rf["ap"] <= rf["ci_high"] + 1e-9).all()
        others = t[t["fusion"] != "rank_fusion"]
        assert others["diff"].notna().all() and others["diff_ci_low"].notna().all()
    sp = pooled[pooled["table"] == "P"]
    assert set(sp["split"]) == {"pixel", "image"} and (sp["floor"] > 0).all()
    ts = pd.read_csv(out / "tableS.csv", index_col=0)
    assert (
        list(ts.columns) == ["0.01", "0.02", "0.03", "0.04", "0.05"]
        and ts.index[0] == "rank_fusion"
    )
    md = (out / "tableS.md").read_text()
    assert "floor, fused set (mean AP of random orders)" in md and "[" in md
    assert "chance band, fused set" in md and "positive rate (not the floor)" in md
    # every row's floor lies in its own chance band, and above the positive rate (method §9)
    assert (sp["chance_low"] <= sp["floor"]).all() and (sp["floor"] <= sp["chance_high"]).all()
    st = pooled[pooled["table"] == "S"]
    assert (st["floor"] > st["positive_rate"]).all()
    cmp_ = (out / "comparisons.md").read_text()
    assert re.search(r"score max - rank fusion = [+-]\d\.\d\d \[[+-]\d\.\d\d, [+-]\d\.\d\d\]", cmp_)
    # the fixture shows the confound: Table I carries the warning, in the .md and in run.json
    assert "WARNING (Table I)" in (out / "table1.md").read_text() and rec["warnings"]["I"]
    for stem in ("table1", "tableS", "tableP", "localization"):
        head, tex = (out / f"{stem}.tex").read_text().split("\n", 1)
        assert head == "% localizer: autoencoder"  # a comment: \input works as it did
        assert tex.startswith(r"\begin{tabular}") and tex.rstrip().endswith(r"\end{tabular}")


def test_reproduce_prints_the_tables_in_order(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    import shutil

    from harness.cli import main

    from ..conftest import ROOT

    p, _, out = local_run
    shutil.copytree(out, tmp_path / "o")
    args = [
        "reproduce",
        "--config",
        str(ROOT / "datasets" / "fixture.toml"),
        "--data-root",
        str(p.cfg.data_root),
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(args) == 0
    text = capsys.readouterr().out
    marks = [
        text.index(m)
        for m in (
            "Localization quality",
            "Table I:",
            "WARNING (Table I)",
            "Table S:",
            "Table P:",
            "Paired comparisons",
        )
    ]
    assert marks == sorted(marks), marks


def test_bootstrap_sorted_once_equals_each_resample_computed_alone() -> None:
    """The fast bootstrap (one sort, reweighted cumulative sums, blocks of resamples) gives the AP,
    the weighted AP and the stratified AP of every resample computed on its own, to the last bits
    of a float64 (numpy 2.4 sums the strata in another order than the check: 1 ulp, 1e-16)."""
    rng = np.random.default_rng(0)
    n = 3000
    y = rng.random(n) < 0.05
    s = np.round(rng.random(n) + y * 0.3, 2)  # many ties
    sob = rng.random(n) * 0.6
    g = rng.integers(0, 120, n)
    w = rng.random(n) * 5
    c = resample_counts(120, 60, 1)
    edges = np.array([0, 0.02, 0.05, 0.1, 0.2, 0.4, 1.0])
    np.testing.assert_allclose(
        bootstrap_aps(y, s, g, c, block_bytes=1 << 16),
        [weighted_average_precision(y, s, cc[g]) for cc in c],
        rtol=0,
        atol=1e-12,
    )
    np.testing.assert_allclose(
        bootstrap_aps(y, s, g, c, weights=w),
        [weighted_average_precision(y, s, w * cc[g]) for cc in c],
        rtol=0,
        atol=1e-12,
    )
    np.testing.assert_allclose(
        bootstrap_aps(y, s, g, c, strata=(sob, edges)),
        [stratified_ap(y, s, sob, edges, cc[g].astype(float))[0] for cc in c],
        rtol=0,
        atol=1e-12,
    )

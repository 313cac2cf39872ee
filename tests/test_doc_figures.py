"""Every figure the README and ``docs/decisions.md`` quote from the fixture is a command's output.

The figures of fixture *variants* (a training budget, projection dims, a database stride) come from
the bench case ``fixture-figures`` (``.venv/bin/python -m bench --only fixture-figures``), recorded
in ``results/bench/bench.json`` with its commit; ``bench.md`` marks the rows stale once the code
changes after them. Each phrase below is the text's sentence with the figures as placeholders:
the test formats it from the recorded rows and fails when the text says anything else. The
default row is checked against the suite's own fixture run, so the record is this code's output;
the figures of the default run alone (Table S's floor, band and verdict) are checked against that
run directly.

After a change that moves the figures: rerun the case, then edit the text until this test passes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd
import pytest

from .conftest import ROOT
from .readme_text import manual_text

BENCH = ROOT / "results" / "bench" / "bench.json"
README = ROOT / "README.md"  # stands for the manual: the README and every page of docs/
METHOD = ROOT / "docs" / "decisions.md"  # the choices measured on the fixture

NAMES = {
    "d": "default",
    "e": "epochs=6",
    "p256": "dim=256",
    "p128": "dim=128",
    "p64": "dim=64",
    "p32": "dim=32",
    "p64w": "dim=64 whiten",
    "s9": "db_stride_m=9",
}

#: (file, phrase) with ``{variant[figure]}`` placeholders (see NAMES and the bench case's figures).
PHRASES: list[tuple[Path, str]] = [
    (
        README,
        "R@1 {e[recall_at_1]:.3f} -> {d[recall_at_1]:.3f} on the fixture (6,000 instead of "
        "18,000 sample-steps)",
    ),
    (
        README,
        "R@1 {d[recall_at_1]:.3f} -> {p256[recall_at_1]:.3f}, Table I rank w/o fusion "
        "{d[t1_rank_no_fusion_003]:.2f} -> {p256[t1_rank_no_fusion_003]:.2f} (RoC-max 0.03) at "
        "dim 256",
    ),
    (
        README,
        "`db_stride_m = 9` halves the database: R@1 {d[recall_at_1]:.2f} -> "
        "{s9[recall_at_1]:.2f}, Table I rank w/o fusion {d[t1_rank_no_fusion_005]:.2f} -> "
        "{s9[t1_rank_no_fusion_005]:.2f}, rank fusion {d[t1_rank_fusion_005]:.2f} -> "
        "{s9[t1_rank_fusion_005]:.2f}",
    ),
    (
        METHOD,
        "6 epochs x 3,000 crops (18,000 sample-steps) took {e[train_s]:.0f} s of training "
        "against {d[train_s]:.0f} s for the budget; R@1 {e[recall_at_1]:.3f} -> "
        "{d[recall_at_1]:.3f}, Table I rank fusion {e[t1_rank_fusion_005]:.2f} -> "
        "{d[t1_rank_fusion_005]:.2f}, Table S rank fusion {e[ts_rank_fusion_005]:.2f} -> "
        "{d[ts_rank_fusion_005]:.2f} and score max {e[ts_score_max_005]:.2f} -> "
        "{d[ts_score_max_005]:.2f} (RoC-max 0.05). The budget {t_stop} of its "
        "{d[train_steps]} steps.",
    ),
    *(
        (
            METHOD,
            f"| {label} | {{{v}[recall_at_1]:.3f}} | {{{v}[clean_recall_at_1]:.3f}} | "
            f"{{{v}[median_r]:.3f}} | {{{v}[t1_rank_fusion_003]:.2f}} | "
            f"{{{v}[t1_rank_no_fusion_003]:.2f}} | {{{v}[t1_score_max_005]:.2f}} |",
        )
        for v, label in (
            ("d", "1024 (full) | -"),
            ("p256", "256 | no"),
            ("p128", "128 | no"),
            ("p64", "64 | no"),
            ("p32", "32 | no"),
            ("p64w", "64 | yes"),
        )
    ),
    (
        METHOD,
        "`dim = 256` changes R@1 by {dim256_diff:+.3f} there ({d[recall_at_1]:.4f} with the full "
        "descriptor, {p256[recall_at_1]:.4f} at 256)",
    ),
    (
        METHOD,
        "{s9[frames_not_described_min]}-{s9[frames_not_described_max]} of each session's 64 frames "
        "are then neither proposed nor encoded, and the autoencoder trains on the others): "
        "{s9[places_lost]} of {d[subimages]:,} query subimages lose their place, R@1 goes "
        "{d[recall_at_1]:.2f} -> {s9[recall_at_1]:.2f}, median r {d[median_r]:.3f} -> "
        "{s9[median_r]:.3f}, Table I at RoC-max 0.05: rank fusion {d[t1_rank_fusion_005]:.2f} -> "
        "{s9[t1_rank_fusion_005]:.2f}, rank w/o fusion {d[t1_rank_no_fusion_005]:.2f} -> "
        "{s9[t1_rank_no_fusion_005]:.2f}, score max {d[t1_score_max_005]:.2f} -> "
        "{s9[t1_score_max_005]:.2f}; Table S: rank fusion {d[ts_rank_fusion_005]:.2f} -> "
        "{s9[ts_rank_fusion_005]:.2f}, score max {d[ts_score_max_005]:.2f} -> "
        "{s9[ts_score_max_005]:.2f}.",
    ),
    (
        METHOD,
        "so it landed at the positive rate on the fixture ({d[t1_rank_fusion_asc_005]:.2f} against "
        "a positive rate of {d[t1_positive_rate_005]:.2f} at RoC-max 0.05)",
    ),
    (
        METHOD,
        "With the paper's descending order (`rank_fusion`) the same ranks give "
        "{d[t1_rank_fusion_005]:.2f}. But `cover_count` (N alone) and `size_prior` (1 - SoB alone) "
        "reach {d[t1_cover_count_005]:.2f} and {d[t1_size_prior_005]:.2f} on the fixture too",
    ),
]


def recorded() -> dict[str, dict]:
    """Variant name -> its figures, from the tracked bench record."""
    rows = json.loads(BENCH.read_text())["results"]
    out = {
        r["case"].removeprefix("fixture figures [").removesuffix("]"): r["figures"]
        for r in rows
        if r.get("group") == "fixture-figures"
    }
    assert set(NAMES.values()) <= set(out), "run: python -m bench --only fixture-figures"
    return out


def _flat(text: str) -> str:
    """The text with its line breaks as spaces (a phrase may wrap anywhere)."""
    return " ".join(text.split())


def test_every_quoted_fixture_figure_is_the_recorded_output() -> None:
    figs = recorded()
    v = {k: figs[name] for k, name in NAMES.items()}
    extra = {
        "dim256_diff": v["p256"]["recall_at_1"] - v["d"]["recall_at_1"],
        "t_stop": (
            "stopped early, at step {d[train_steps]}".format(**v)
            if v["d"]["stopped_early"]
            else "did not stop early there: the held-out loss still fell at the last"
        ),
    }
    texts = {README: _flat(manual_text()), METHOD: _flat(METHOD.read_text())}
    wrong = []
    for path, phrase in PHRASES:
        want = _flat(phrase.format(**v, **extra))
        if want not in texts[path]:
            wrong.append(f"{path.name}: {want}")
    assert not wrong, "the text does not say what the command measured:\n" + "\n".join(wrong)


def test_the_recorded_default_row_is_this_codes_fixture_run(local_run: tuple) -> None:
    """The record's default figures equal the suite's own run of the fixture (so the record is
    not older than the code; the variants share its stages up to the setting they change)."""
    import importlib

    from .stage_digests import skip_unless_recorded_model

    figures = importlib.import_module("bench.cases.fixture_figures").figures
    _, _, out = local_run
    now, rec = figures(out), recorded()["default"]
    assert set(now) - {"train_s"} <= set(rec), set(now) - set(rec)
    skip_unless_recorded_model(out)
    for k, x in now.items():
        if k == "train_s":  # a time: the machine's, not the code's
            continue
        assert k in rec, f"{k}: not in the record; run python -m bench --only fixture-figures"
        if isinstance(x, float):
            assert math.isclose(x, rec[k], rel_tol=1e-6, abs_tol=1e-9), (k, x, rec[k])
        else:
            assert x == rec[k], (k, x, rec[k])


def test_the_readme_table_s_sentence_is_the_fixture_runs(local_run: tuple) -> None:
    """The README's Table S figures (floor, band, random row, rank fusion and its interval) and the
    positive control in *Changes*, from the run's own summary."""
    from .stage_digests import skip_unless_recorded_model

    _, _, out = local_run
    skip_unless_recorded_model(out)
    s = pd.read_parquet(out / "splits" / "summary.parquet")
    ts = s[(s["table"] == "S") & (s["roc_max"].round(6) == 0.05)].set_index("fusion")
    rf, rnd = ts.loc["rank_fusion"], ts.loc["random"]
    mark = {"above": "▲", "below": "▼"}.get(str(rnd["verdict"]), "○")
    text = _flat(manual_text())
    rf_mark = {"above": "▲", "below": "▼"}.get(str(rf["verdict"]), "○")
    for phrase in (
        f"RoC-max 0.05 reads: floor {rf['floor']:.2f} (the positive rate is "
        f"{rf['positive_rate']:.3f}), chance band {rf['chance_low']:.2f}-{rf['chance_high']:.2f}, "
        f"the `random` row {rnd['ap']:.2f} `{mark}`, rank fusion {rf['ap']:.2f} "
        f"[{rf['ci_low']:.2f}, {rf['ci_high']:.2f}] `{rf_mark}`.",
        f"(on the fixture's Table S, {rf['positive_rate']:.3f} against {rf['floor']:.2f})",
        f"Rank fusion is now above chance at every RoC-max: at 0.05, {rf['ap']:.2f} against a "
        f"chance band up to {rf['chance_high']:.2f}, and its paired difference from random clear "
        f"of 0 (lower end {rf['vs_random_diff_ci_low']:.3f})",
    ):
        assert phrase in text, phrase
    ts_all = s[
        (s["table"] == "S") & (s["fusion"] == "rank_fusion") & (s["proposal_method"] == "all")
    ]
    ts_all = ts_all[ts_all["season_pair"] == "all"]
    assert (ts_all["verdict"] == "above").all(), ts_all[["roc_max", "verdict"]]  # "every RoC-max"


@pytest.mark.parametrize("path", [README, METHOD])
def test_no_figure_of_an_older_fixture_world_is_left(path: Path) -> None:
    """The figures of the world before this one (R@1 0.278, rank w/o fusion 0.46, 2,232 query
    subimages) are gone from the text."""
    text = manual_text() if path == README else path.read_text()
    for old in ("0.278", "2,232", "0.46 -> "):
        assert old not in text, old

"""method §14: the field's rank-fusion rules against ranx's own fusion of the same lists.

Each original box is one ranked list of places; a fused box fuses the lists of the originals that
cover it. In ranx's terms a fused box is a query, each covering original a run, and the true place
a document at position ``rank' = L + 1 - rank`` of its run (least similar first). ranx is a test
dependency only (MIT); the harness writes the formulas from their definitions.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from harness.fusion.fuse import loc_from_cover
from harness.fusion.rules import standard_rule

# ranx's kernels are numba functions: compiled, they cost a minute and a half of a fresh venv's CI
# for lists of a few dozen places; interpreted, they are the same Python source in milliseconds.
# Only ranx imports numba, and only here.
os.environ.setdefault("NUMBA_DISABLE_JIT", "1")
ranx = pytest.importorskip("ranx")


def _run(rank: int, length: int, qid: str = "q") -> object:
    """One ranked list of ``length`` places sorted least similar first, the true place ``T`` at
    ``rank' = length + 1 - rank``; each place's score is its normalised rank (position / L, most
    similar first), so the list's descending order is least similar first."""
    names = [f"p{j}" for j in range(1, length)]  # the same other places in every list
    names.insert(rank - 1, "T")
    return ranx.Run({qid: {name: (j + 1) / length for j, name in enumerate(names)}})


def _random_case(rng: np.random.Generator, same_length: bool):
    """Random lists, covers and ranks. Lists of different lengths hold different places; compiled
    by numba, ranx 0.3.21's CombSUM/CombMNZ lose documents then (a comprehension in
    ``_comb_sum`` rebinds its loop variable), interpreted they do not."""
    n, m = int(rng.integers(2, 7)), int(rng.integers(1, 6))
    lengths = np.full(n, int(rng.integers(3, 40))) if same_length else rng.integers(3, 40, n)
    rank = np.array([int(rng.integers(1, L + 1)) for L in lengths])
    cover = np.zeros((m, n), bool)
    for i in range(m):  # ranx fuses two runs or more
        cover[i, rng.choice(n, size=int(rng.integers(2, n + 1)), replace=False)] = True
    return cover, rank, lengths


def _ranx_value(cover_row, rank, lengths, method: str, params: dict | None = None) -> float:
    runs = [_run(int(rank[k]), int(lengths[k])) for k in np.flatnonzero(cover_row)]
    fused = ranx.fuse(runs, norm=None, method=method, params=params or {})
    return float(fused.to_dict()["q"]["T"])


@pytest.mark.parametrize(
    ("rule", "method", "params"),
    [
        ("rrf", "rrf", {"k": 60}),
        ("rrf", "rrf", {"k": 5}),
        ("isr", "isr", {}),
        ("combmnz", "mnz", {}),
    ],
)
def test_rules_equal_ranx_fuse(rule, method, params):
    rng = np.random.default_rng(14)
    for _ in range(20):
        cover, rank, lengths = _random_case(rng, same_length=False)
        mine = standard_rule(cover, rule, rank, lengths, c=float(params.get("k", 60)))
        for i in range(len(cover)):
            assert mine[i] == pytest.approx(_ranx_value(cover[i], rank, lengths, method, params))


def test_borda_is_ranx_bordafuse_normalised():
    """ranx's BordaFuse gives the place ``L + 1 - rank'_k = rank_k`` points in each list (all
    lists over the same L places) and sums them; method §14 takes their mean of ``(rank - 1) / L``,
    so ``ranx = N * (L * borda + 1)`` exactly."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        cover, rank, lengths = _random_case(rng, same_length=True)
        mine = standard_rule(cover, "borda", rank, lengths)
        for i in range(len(cover)):
            n, L = int(cover[i].sum()), int(lengths[0])
            got = _ranx_value(cover[i], rank, lengths, "bordafuse")
            assert n * (L * mine[i] + 1) == pytest.approx(got)


def test_rules_through_the_fusion_stage_and_their_direction():
    """The stage reads ``r = rank / L``: the same values as from integer ranks, and each rule
    puts the box whose lists rank the true place last (the strongest sign of change) first."""
    cover = np.array([[True, True, False], [False, True, True], [True, False, True]])
    L = np.array([10.0, 20.0, 8.0])
    rank = np.array([10.0, 19.0, 1.0])  # lists 0 and 1 lose the place, list 2 finds it first
    for rule in ("rrf", "combmnz", "borda", "isr"):
        via_r = loc_from_cover(cover, rule, r=rank / L, d=np.full(3, np.nan), L=L, rrf_c=60.0)
        assert via_r == pytest.approx(standard_rule(cover, rule, rank, L))
        assert np.argmax(via_r) == 0, rule


# ---------------------------------------------------------------- Holm's correction (issue 38)


def test_holm_marks_what_the_adjusted_p_values_reject():
    """Holm's step-down test against its adjusted p-values, written out again:
    ``p_adj(i) = max_{j <= i} min(1, (m - j + 1) p_(j))``, rejected where ``p_adj <= alpha``;
    untested differences (NaN) are neither counted nor marked."""
    from harness.evaluate.metrics import holm

    rng = np.random.default_rng(38)
    for _ in range(300):
        m = int(rng.integers(1, 30))
        p = rng.choice([rng.uniform(0, 0.01), rng.uniform(0, 1)], size=m) * rng.uniform(0, 1, m)
        p[rng.uniform(size=m) < 0.1] = np.nan
        tested = np.flatnonzero(np.isfinite(p))
        order = tested[np.argsort(p[tested], kind="stable")]
        adj, run = np.full(m, np.nan), 0.0
        for j, i in enumerate(order):
            run = max(run, min(1.0, (len(order) - j) * p[i]))
            adj[i] = run
        want = np.isfinite(adj) & (adj <= 0.05)
        assert holm(p, 0.05).tolist() == want.tolist()


def test_the_paired_p_value_is_the_normal_tail_of_the_bootstrap_difference():
    from harness.evaluate.metrics import paired_difference

    rng = np.random.default_rng(1)
    a = rng.normal(0.30, 0.05, 4000)
    b = a - rng.normal(0.10, 0.05, 4000)  # a - b ~ N(0.10, 0.05): z = 2
    got = paired_difference(a, b, 0.30, 0.20, 0.95)
    assert got["p_value"] == pytest.approx(0.0455, abs=0.004)  # 2 (1 - Phi(2))
    assert paired_difference(a, a, 0.3, 0.3, 0.95)["p_value"] == 1.0  # nothing to test

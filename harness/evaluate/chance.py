"""Floor, chance band, ceiling and the one verdict rule (method §9, *Floor, chance and ceiling*).

The **floor** of a figure is the mean of the same figure over seeded random orders of the same
samples (uniform scores through the same strata, pixel maps or candidate boxes); the **chance
band** is the 5th to 95th percentile of those draws. 101-point interpolated AP of a random order
is biased upward, the more so the fewer the positives, so the positive rate is not the floor; it
is reported under its own name.

A figure is **above chance** only when it exceeds the band's top *and* its paired bootstrap
difference from the ``random`` baseline has an interval clear of 0 (:func:`verdict`); **below
chance** symmetrically; otherwise it **cannot be told from chance**. Every colour, verdict column
and WARNING line of the harness comes from :func:`verdict`.

All draws are vectorised: a block of draws is one ``(draws, samples)`` score matrix, sorted once
along its rows (:func:`aps_of_rows`).
"""

from __future__ import annotations

import functools
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from harness.evaluate.config import EvalSettings
from harness.evaluate.metrics import RECALL_GRID

#: The fewest random orders a floor may rest on (method §9).
MIN_DRAWS = 200
#: The chance band: these percentiles of the random draws.
BAND = (5.0, 95.0)

#: Verdict ids and the words every table, page and warning uses for them.
VERDICT_WORDS = {
    "above": "above chance",
    "below": "below chance",
    "chance": "cannot be told from chance",
    "untested": "no interval: not tested against chance",
    "undefined": "undefined (no positive)",
    "few": "too few positives",
    "baseline": "above chance, not above a baseline row",
}
#: One mark per verdict for narrow cells (markdown, console); LaTeX has its own. ``few`` has none:
#: its cell says "too few positives (n)" in words (:func:`few_text`).
VERDICT_MARKS = {
    "above": "▲",
    "below": "▼",
    "chance": "○",
    "untested": "",
    "undefined": "",
    "few": "",
    "baseline": "△",
}
VERDICT_TEX = {
    "above": r"$^{\blacktriangle}$",
    "below": r"$^{\blacktriangledown}$",
    "chance": r"$^{\circ}$",
    "untested": "",
    "undefined": "",
    "few": "",
    "baseline": r"$^{\vartriangle}$",
}
#: ``[report] min_positive_images``'s default: the fewest query images holding a positive on
#: which a figure earns a verdict (method §9, *Evidence before a verdict*).
MIN_POSITIVE_IMAGES = 5
#: The legend line under every table that shows the marks.
MARK_LEGEND = (
    "▲ above chance: AP above the chance band (95th percentile of random orders of the same "
    "samples) and its paired bootstrap difference from random clear above 0; ▼ below chance "
    "(symmetrically); ○ cannot be told from chance (method §9)."
)


def _finite(*v: float) -> bool:
    return all(x == x and abs(x) != float("inf") for x in v)


@dataclass(frozen=True)
class ChanceSettings:
    """How a table's method §9 figures are measured (``[report]`` and the run's seed).

    ``draws`` random orders for the floor, ``n_boot`` bootstrap resamples of query images for
    the intervals at level ``ci``, ``seed`` for both, and ``needed`` positive images before a
    figure earns a verdict (``[report] min_positive_images``).
    """

    draws: int = MIN_DRAWS
    n_boot: int = 1000
    ci: float = 0.95
    seed: int = 0
    needed: int = MIN_POSITIVE_IMAGES

    @classmethod
    def of(cls, cfg: EvalSettings) -> ChanceSettings:
        """A run's: ``[report]`` chance_draws, bootstrap, ci, min_positive_images, and its seed."""
        rp = cfg.report
        return cls(rp.chance_draws, rp.bootstrap, rp.ci, cfg.seed, rp.min_positive_images)


@dataclass(frozen=True)
class Evidence:
    """What a figure rests on (method §9, *Evidence before a verdict*).

    ``positive_images``: the query images holding a positive sample of the figure; ``needed``:
    ``[report] min_positive_images``. A bootstrap over query images can vary a figure only when
    at least two of them hold a positive (with one, every resample that holds it holds the same
    positives), so the figure earns a verdict with at least ``max(needed, 2)``. (Whether the
    resamples' values happen to differ is no test: a perfect AP over 24 positive images is 1.00 in
    every resample, and is still evidence.)
    """

    positive_images: int
    needed: int = MIN_POSITIVE_IMAGES

    @property
    def enough(self) -> bool:
        """Whether the figure may carry a verdict at all."""
        return self.positive_images >= max(self.needed, 2)


def versus_no_pixel(verdict_id: str, vs_low: float) -> str:
    """Method §13.3 on top of :func:`verdict`: ``above`` only when also clear of the no-pixel rows.

    A detector above chance stays ``above`` only when the low end of its paired bootstrap
    difference from the best no-pixel baseline is above 0; else ``baseline`` (above chance, not
    above a baseline that reads no pixel: no colour).
    """
    return "baseline" if verdict_id == "above" and not vs_low > 0 else verdict_id


def verdict(
    ap: float,
    chance_low: float,
    chance_high: float,
    vs_lo: float,
    vs_hi: float,
    evidence: Evidence | None = None,
) -> str:
    """Method §9's one rule: ``above``, ``below``, ``chance``, ``few``, ``untested``, ``undefined``.

    Args:
        ap: the figure.
        chance_low: the bottom of its chance band (5th percentile of random orders).
        chance_high: the top of its chance band (95th percentile of random orders).
        vs_lo: the low end of its paired bootstrap difference from the ``random`` baseline (NaN
            when no bootstrap was drawn: then the figure is ``untested``, never above).
        vs_hi: the high end of that interval.
        evidence: what the figure rests on: too few positive query images (so few that the
            bootstrap cannot vary the figure) give ``few`` (no verdict, no colour) whatever the AP.
    """
    if not _finite(ap, chance_low, chance_high):
        return "undefined"
    if evidence is not None and not evidence.enough:
        return "few"
    if not _finite(vs_lo, vs_hi):
        return "untested"
    if ap > chance_high and vs_lo > 0:
        return "above"
    if ap < chance_low and vs_hi < 0:
        return "below"
    return "chance"


def few_text(n: int) -> str:
    """A ``few`` cell's words: ``too few positives (n)``, n the positive query images."""
    return f"{VERDICT_WORDS['few']} ({int(n)})"


def few_warning(cells: int, needed: int) -> str:
    """The line under a table with ``cells`` cells of verdict ``few``."""
    return (
        f"WARNING: {cells} cell{'s' if cells != 1 else ''} rest on fewer than {max(needed, 2)} "
        "query images holding a positive, too few for the bootstrap over query images to vary "
        'them: each shows its AP with "too few positives (n)" and no verdict or colour (method §9, '
        "evidence before a verdict; [report] min_positive_images)."
    )


def draw_seed(seed: int, *key: object) -> int:
    """A seed for the random orders of one figure: the run's seed and what the draws depend on.

    The same samples get the same floor whatever the order in which figures are computed.
    """
    return (int(seed) * 1_000_003 + zlib.crc32(repr(key).encode())) % (2**63)


def aps_of_rows(
    labels: np.ndarray, scores: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """101-point interpolated AP (method §9) of every row of ``scores`` against the same labels.

    Equal to :func:`harness.evaluate.metrics.weighted_average_precision` of each row (tied scores
    enter together; ``weights`` default to 1). One stable sort per row.

    Args:
        labels: (n,) bool.
        scores: (B, n) one score vector per row.
        weights: optional (n,) sample weights (pixel areas).

    Returns:
        (B,) APs; NaN for every row when there is no positive weight.
    """
    y = np.asarray(labels, bool)
    s = np.asarray(scores, np.float64)
    b, n = s.shape
    w = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    if n == 0 or not (w * y).sum() > 0:
        return np.full(b, np.nan)
    order = np.argsort(-s, axis=1, kind="stable")
    ss = np.take_along_axis(s, order, axis=1)
    wy, wn = (w * y)[order], (w * ~y)[order]
    tp, fp = np.cumsum(wy, axis=1), np.cumsum(wn, axis=1)
    end = np.ones((b, n), bool)
    end[:, :-1] = ss[:, 1:] != ss[:, :-1]  # only the last of a tied group is a point
    tot = tp + fp
    prec = np.where(end & (tot > 0), tp / np.where(tot > 0, tot, 1.0), 0.0)
    rec = tp / tp[:, -1:]
    pmax = np.maximum.accumulate(prec[:, ::-1], axis=1)[:, ::-1]
    # first point with recall >= R in every row: one searchsorted over rows laid end to end
    off = 2.0 * np.arange(b)[:, None]
    idx = np.searchsorted((rec + off).ravel(), (RECALL_GRID[None, :] - 1e-12 + off).ravel())
    idx = idx.reshape(b, -1) - n * np.arange(b)[:, None]
    ok = idx < n
    vals = np.take_along_axis(pmax, np.minimum(idx, n - 1), axis=1)
    return np.where(ok, vals, 0.0).mean(axis=1)


def random_draws(
    figure: Callable[[np.ndarray], np.ndarray],
    n_units: int,
    draws: int,
    seed: int,
    block_bytes: int = 32 << 20,
) -> np.ndarray:
    """``figure`` of ``draws`` uniform random score vectors over ``n_units`` scored units.

    ``figure`` maps a (b, n_units) block of scores to (b,) figures (through whatever strata, maps
    or boxes the real figure goes through). Blocks keep the score matrix under ``block_bytes``.
    """
    rng = np.random.default_rng(seed)
    step = max(1, int(block_bytes // max(8 * max(n_units, 1) * 6, 1)))
    out = []
    for b0 in range(0, draws, step):
        out.append(figure(rng.random((min(step, draws - b0), n_units))))
    return np.concatenate(out) if out else np.zeros(0)


def summarise(aps: np.ndarray) -> tuple[float, float, float]:
    """(floor, chance_low, chance_high): the mean and the band's percentiles of the draws."""
    v = np.asarray(aps, np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return float("nan"), float("nan"), float("nan")
    lo, hi = np.percentile(v, BAND)
    return float(v.mean()), float(lo), float(hi)


@functools.lru_cache(maxsize=4096)
def order_aps(n: int, p: int, draws: int, seed: int) -> np.ndarray:
    """101-point APs of ``draws`` random orders of ``n`` samples holding ``p`` positives.

    A random order of distinct scores is a random permutation of the labels (rows shuffled by
    ``Generator.permuted``, no sort); precision at the j-th positive, found at 1-based position
    ``pos_j``, is ``j / pos_j``, and ``p(R)`` is the largest of those from the first positive
    with ``j / p >= R`` on. Equal to :func:`harness.evaluate.metrics.average_precision` of each
    order.
    """
    if p == 0:
        return np.full(draws, np.nan)
    k = np.maximum(np.ceil((RECALL_GRID - 1e-12) * p).astype(np.int64), 1) - 1
    rng = np.random.default_rng(seed)
    step = max(1, (16 << 20) // max(n, 1))
    out = []
    for b0 in range(0, draws, step):
        b = min(step, draws - b0)
        rows = rng.permuted(np.broadcast_to(np.arange(n) < p, (b, n)), axis=1)
        pos = np.nonzero(rows)[1].reshape(b, p) + 1.0
        prec = np.arange(1, p + 1) / pos
        pmax = np.maximum.accumulate(prec[:, ::-1], axis=1)[:, ::-1]
        out.append(pmax[:, k].mean(axis=1))
    res = np.concatenate(out)
    res.flags.writeable = False  # cached: the same counts and seed give the same draws
    return res


def plain_chance(labels: np.ndarray, draws: int, seed: int) -> tuple[float, float, float]:
    """Floor and band of a plain 101-point AP: random orders of the samples.

    Depends on the number of samples and positives only, so it is seeded by those.
    """
    y = np.asarray(labels, bool)
    n, p = len(y), int(y.sum())
    return summarise(order_aps(n, p, draws, draw_seed(seed, n, p)))


def stratum_index(sob: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Each sample's SoB stratum (method §8: ``[lo, hi)``, the last one closed); -1 outside."""
    e = np.asarray(edges, np.float64)
    sb = np.asarray(sob, np.float64)
    k = np.clip(np.searchsorted(e, sb, side="right") - 1, 0, len(e) - 2)
    return np.where((sb >= e[0]) & (sb <= e[-1]), k, -1)


def stratified_chance(
    labels: np.ndarray, sob: np.ndarray, edges: np.ndarray, draws: int, seed: int
) -> tuple[float, float, float]:
    """Floor and band of the size-stratified AP (method §8): random orders within the same strata.

    Each draw is the positives-weighted mean of the strata's random-order APs (strata with a
    positive and a negative take part), as :func:`harness.evaluate.metrics.stratified_ap` weighs
    them.
    """
    y = np.asarray(labels, bool)
    k = stratum_index(sob, edges)
    total = np.zeros(draws)
    weight = 0.0
    for j in range(len(edges) - 1):
        sel = k == j
        n, p = int(sel.sum()), int((sel & y).sum())
        if p == 0 or p == n:
            continue
        total += p * order_aps(n, p, draws, draw_seed(seed, n, p))
        weight += p
    if weight == 0:
        return float("nan"), float("nan"), float("nan")
    return summarise(total / weight)


def gap_closed(ap: float, floor: float, ceiling: float) -> float:
    """``(AP - floor) / (ceiling - floor)``: the share of the reachable gap a method closes."""
    if not _finite(ap, floor, ceiling) or ceiling <= floor:
        return float("nan")
    return (ap - floor) / (ceiling - floor)

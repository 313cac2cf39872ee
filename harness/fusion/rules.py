"""The fusion rules of the fused set, one small function each (SPEC sections 7 and 14).

Each takes the cover matrix (``cover[i, k]``: original box k contains fused box i), the
originals' normalised ranks ``r = rank / L``, their relevance scores ``d`` and list lengths
``L``, and returns one LoC per fused box (higher = more likely changed). :func:`rule` attaches a
function to its record in the method catalogue (``harness.methods.FUSION_RULES``), the same
record a user's ``fusion.register_method`` makes, so reproduce, Table L and detect find the
paper's rules and a user's in one place.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from harness.methods import FUSION_RULES, STANDARD_RULES

Loc = Callable[..., np.ndarray]


def rule(name: str) -> Callable[[Loc], Loc]:
    """Attach the decorated function to catalogue record ``name``."""

    def attach(fn: Loc) -> Loc:
        FUSION_RULES[name] = dataclasses.replace(FUSION_RULES[name], loc=fn)
        return fn

    return attach


def r_desc_of(r: np.ndarray, L: np.ndarray) -> np.ndarray:
    """``r' = (L + 1 - rank) / L`` from ``r = rank / L`` (SPEC section 6)."""
    r, L = np.asarray(r, np.float64), np.asarray(L, np.float64)
    return np.asarray((L + 1.0) / L - r, np.float64)


def _subset_cover(cover: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Where a row covers more than k originals, keep a random k of them (in row order)."""
    out = cover.copy()
    for i in np.nonzero(cover.sum(1) > k)[0]:
        idx = np.nonzero(cover[i])[0]
        keep = rng.choice(idx, size=k, replace=False)
        out[i] = False
        out[i, keep] = True
    return out


def _paper(cover: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """SPEC section 7's fusion: ``N * sum(1 / r')`` over the covering originals."""
    return np.asarray(cover.sum(1) * (cover * inv[None, :]).sum(1), np.float64)


@rule("rank_fusion")
def rank_fusion(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The paper's rank fusion: ``N * sum(1 / r')``."""
    return _paper(cover, 1.0 / r_desc_of(r, L))


def _rank_fusion_le(k: int) -> Loc:
    def le(
        cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray, *, seed: int = 0
    ) -> np.ndarray:
        sub = _subset_cover(cover, k, np.random.default_rng(seed))
        return _paper(sub, 1.0 / r_desc_of(r, L))

    le.__doc__ = f"Rank fusion over at most {k} covering originals (a random {k}, per image seed)."
    return le


rank_fusion_le2 = rule("rank_fusion_le2")(_rank_fusion_le(2))
rank_fusion_le3 = rule("rank_fusion_le3")(_rank_fusion_le(3))


@rule("rank_fusion_raw")
def rank_fusion_raw(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The paper's variant 1: ``1 / (L + 1 - rank)`` in place of ``1 / r'``."""
    return _paper(cover, 1.0 / (r_desc_of(r, L) * np.asarray(L, np.float64)))


@rule("rank_fusion_asc")
def rank_fusion_asc(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The paper's variant 2, ascending order (SPEC's earlier formula): ``1 / (N * sum(1/r))``."""
    return np.asarray(1.0 / (cover.sum(1) * (cover * (1.0 / r)[None, :]).sum(1)), np.float64)


@rule("score_max")
def score_max(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The largest relevance score ``d`` of the covering originals."""
    return np.asarray(np.where(cover, d[None, :], -np.inf).max(1))


@rule("score_sum")
def score_sum(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The sum of the covering originals' relevance scores ``d``."""
    return np.asarray((cover * d[None, :]).sum(1), np.float64)


@rule("cover_count")
def cover_count(cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray) -> np.ndarray:
    """How many originals cover the box: a baseline that reads no pixel."""
    return np.asarray(cover.sum(1), np.float64)


def standard_rule(
    cover: np.ndarray, name: str, rank: np.ndarray, L: np.ndarray, c: float = 60.0
) -> np.ndarray:
    """LoC of the fused boxes by one of the field's rank-fusion rules (SPEC section 14).

    Each original box k is one ranked list of ``L_k`` places; ``rank_k`` is its true place's
    position sorted most similar first, so ``rank'_k = L_k + 1 - rank_k`` is its position sorted
    least similar first (1 = the strongest sign of change). A fused box fuses the lists of the
    originals that cover it (``N`` of them). The formulas are ranx's (``rrf``, ``combmnz``
    over rank-normalised scores, ``borda``, ``isr``), written here from their definitions.

    Args:
        cover: (m, n) bool: original k contains fused box i.
        name: ``rrf``, ``combmnz``, ``borda`` or ``isr``.
        rank: (n,) the true place's rank in each list, most similar first (1..L).
        L: (n,) the lists' lengths.
        c: RRF's constant (``[fusion] rrf_c``).
    """
    rank, L = np.asarray(rank, np.float64), np.asarray(L, np.float64)
    cov = cover.astype(np.float64)
    n = cov.sum(1)
    rank_d = L + 1.0 - rank
    if name == "rrf":
        return np.asarray(cov @ (1.0 / (c + rank_d)), np.float64)
    if name == "combmnz":
        return np.asarray(n * (cov @ (rank / L)), np.float64)
    if name == "borda":
        return np.asarray((cov @ ((rank - 1.0) / L)) / np.maximum(n, 1.0), np.float64)
    if name == "isr":
        return np.asarray(n * (cov @ (1.0 / rank_d**2)), np.float64)
    raise ValueError(f"unknown rank-fusion rule {name!r}; known: {STANDARD_RULES}")


def _standard(name: str) -> Loc:
    def fn(
        cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray, *, rrf_c: float = 60.0
    ) -> np.ndarray:
        return standard_rule(cover, name, np.rint(r * L), L, rrf_c)

    fn.__doc__ = f"SPEC 14's {name} over the covering originals' lists (:func:`standard_rule`)."
    return fn


rrf = rule("rrf")(_standard("rrf"))
combmnz = rule("combmnz")(_standard("combmnz"))
borda = rule("borda")(_standard("borda"))
isr = rule("isr")(_standard("isr"))


# ------------------------------------------------------------- the image baselines (kind "image")


@rule("size_prior")
def size_prior(fused: np.ndarray, width: float, height: float, seed: int) -> np.ndarray:
    """1 - SoB: a sample's LoC from its size alone (the baseline that reads no pixel)."""
    area = (fused[:, 2] - fused[:, 0]) * (fused[:, 3] - fused[:, 1])
    return np.asarray(1.0 - area / float(width * height), np.float64)


@rule("random")
def random_loc(fused: np.ndarray, width: float, height: float, seed: int) -> np.ndarray:
    """Uniform in [0, 1), reproducible per image (``seed``: the query image's)."""
    return np.random.default_rng(seed).random(len(fused))

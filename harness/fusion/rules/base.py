"""What the fusion rules share: their decorator, ``r'``, the paper's sum, the field's rules' form.

A rule takes the cover matrix (``cover[i, k]``: original box k contains fused box i), the
originals' normalised ranks ``r = rank / L``, their relevance scores ``d`` and list lengths
``L``, and returns one LoC per fused box (higher = more likely changed).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from harness.methods import FUSION_RULES, STANDARD_RULES, Registry

Loc = Callable[..., np.ndarray]
#: A rank-fusion rule's formula: (cover as floats, covering count N, rank, rank' = L + 1 - rank,
#: L, RRF's c) -> LoC (method §14).
Formula = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float], np.ndarray]
#: The field's rank-fusion rules' formulas by name (``rrf``, ``combmnz``, ``borda``, ``isr``).
FORMULAS: Registry[Formula] = Registry("rank-fusion formula")


def rule(name: str) -> Callable[[Loc], Loc]:
    """Attach the decorated function to catalogue record ``name``."""

    def attach(fn: Loc) -> Loc:
        FUSION_RULES[name] = dataclasses.replace(FUSION_RULES[name], loc=fn)
        return fn

    return attach


def r_desc_of(r: np.ndarray, L: np.ndarray) -> np.ndarray:
    """``r' = (L + 1 - rank) / L`` from ``r = rank / L`` (method §6)."""
    r, L = np.asarray(r, np.float64), np.asarray(L, np.float64)
    return np.asarray((L + 1.0) / L - r, np.float64)


def paper_sum(cover: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """Method §7's fusion: ``N * sum(1 / r')`` over the covering originals."""
    return np.asarray(cover.sum(1) * (cover * inv[None, :]).sum(1), np.float64)


def standard_rule(
    cover: np.ndarray, name: str, rank: np.ndarray, L: np.ndarray, c: float = 60.0
) -> np.ndarray:
    """LoC of the fused boxes by one of the field's rank-fusion rules (method §14).

    Each original box k is one ranked list of ``L_k`` places; ``rank_k`` is its true place's
    position sorted most similar first, so ``rank'_k = L_k + 1 - rank_k`` is its position sorted
    least similar first (1 = the strongest sign of change). A fused box fuses the lists of the
    originals that cover it (``N`` of them). The formulas are ranx's (``rrf``, ``combmnz``
    over rank-normalised scores, ``borda``, ``isr``), written from their definitions, one module
    each.

    Args:
        cover: (m, n) bool: original k contains fused box i.
        name: ``rrf``, ``combmnz``, ``borda`` or ``isr``.
        rank: (n,) the true place's rank in each list, most similar first (1..L).
        L: (n,) the lists' lengths.
        c: RRF's constant (``[fusion] rrf_c``).
    """
    if name not in FORMULAS:
        raise ValueError(f"unknown rank-fusion rule {name!r}; known: {STANDARD_RULES}")
    rank, L = np.asarray(rank, np.float64), np.asarray(L, np.float64)
    cov = cover.astype(np.float64)
    return np.asarray(FORMULAS[name](cov, cov.sum(1), rank, L + 1.0 - rank, L, c), np.float64)


def standard(name: str) -> Loc:
    """Rank-fusion rule ``name`` as a rule of the fused set (``r``, ``L`` to ranks)."""

    def fn(
        cover: np.ndarray, r: np.ndarray, d: np.ndarray, L: np.ndarray, *, rrf_c: float = 60.0
    ) -> np.ndarray:
        return standard_rule(cover, name, np.rint(r * L), L, rrf_c)

    fn.__doc__ = f"method §14's {name} over the covering originals' lists (:func:`standard_rule`)."
    return fn

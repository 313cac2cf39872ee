"""Method ids, labels and registries: the bottom of the house (it imports nothing of the harness).

Every module that needs to know what a fusion or proposal method is called, how it is labelled
or whether a name is known reads it here, so the config check, the fusion stage, the reports and
the figures share one catalogue and none of them imports another to ask. The functions behind
the names live with their stage (``fusion``, ``proposals``), which register them here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

#: Table I's six rows, in SPEC section 7's order.
FUSION_METHODS = (
    "rank_fusion",
    "rank_fusion_le2",
    "rank_fusion_le3",
    "rank_no_fusion",
    "score_max",
    "score_sum",
)
#: The paper's two variants and the three baselines (SPEC section 7), the separate block of every
#: table.
EXTRA_METHODS = (
    "rank_fusion_asc",
    "rank_fusion_raw",
    "rrf",
    "combmnz",
    "borda",
    "isr",
    "size_prior",
    "cover_count",
    "random",
)
#: The field's standard rank-fusion rules (SPEC section 14): ranks alone, so every localizer
#: (imported lists without scores too) and every pair of localizers can have them.
STANDARD_RULES = ("rrf", "combmnz", "borda", "isr")
#: The methods whose LoC ``harness detect`` can threshold into boxes: fused-set rules of ranks
#: alone (no relevance score, not a baseline).
DETECT_METHODS = ("rank_fusion", "rank_fusion_le2", "rank_fusion_le3", *STANDARD_RULES)
#: Baselines that read no pixel: SPEC section 7's confound warning compares them with the six.
BASELINES = ("size_prior", "cover_count", "random")
ALL_METHODS = FUSION_METHODS + EXTRA_METHODS
#: Methods that need a relevance score ``d`` (a localizer without one cannot have them).
SCORE_METHODS = ("score_max", "score_sum")

#: How every table, figure and page names a fusion method.
METHOD_LABELS = {
    "rank_fusion": "rank fusion",
    "rank_fusion_le2": "rank fusion (<=2)",
    "rank_fusion_le3": "rank fusion (<=3)",
    "rank_no_fusion": "rank w/o fusion",
    "score_max": "score max",
    "score_sum": "score sum",
    "rank_fusion_asc": "rank fusion asc (variant 2)",
    "rank_fusion_raw": "rank fusion raw (variant 1)",
    "rrf": "RRF (reciprocal rank)",
    "combmnz": "CombMNZ",
    "borda": "Borda count",
    "isr": "ISR (inverse square rank)",
    "size_prior": "size prior (no pixel)",
    "cover_count": "cover count (no pixel)",
    "random": "random",
}

#: Fused-set fusion methods registered beside SPEC section 7's (``fusion.register_method``):
#: name -> the function of the cover matrix.
FUSION_REGISTRY: dict[str, Callable[..., Any]] = {}

#: Proposal methods of the harness that are not per-image functions.
SPECIAL_PROPOSALS = ("grid5", "yolo", "file")
#: The built-in per-image proposers (``proposals`` registers their functions).
BUILTIN_PROPOSERS = ("edges", "mser")
#: Per-image proposal methods: name -> function (built-in ones and ``proposals.register_method``).
PROPOSERS: dict[str, Callable[..., Any]] = {}


def known_fusion_methods() -> tuple[str, ...]:
    """Every method ``[fusion] methods`` may list: SPEC section 7's, then registered ones."""
    return (*ALL_METHODS, *FUSION_REGISTRY)


def known_proposal_methods() -> tuple[str, ...]:
    """Every proposal method name ``[proposals] methods`` may list."""
    image = dict.fromkeys((*BUILTIN_PROPOSERS, *PROPOSERS))
    return ("grid5", *image, "yolo", "file")


def ordered_methods(methods: Iterable[str]) -> tuple[str, ...]:
    """The configured methods in table order.

    SPEC section 7's (Table I's six, the variants, the baselines), then registered ones as
    registered.
    """
    want = set(methods)
    return tuple(m for m in known_fusion_methods() if m in want)

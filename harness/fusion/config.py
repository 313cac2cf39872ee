"""The fusion stage's config: ``[fusion]`` (method §7) and its checks."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from harness.checks import check_value
from harness.methods import ALL_METHODS, FUSION_OPTIONS, known_fusion_methods


@dataclass(frozen=True)
class FusionConfig:
    """``[fusion]``: the methods of method §7 that are computed and reported."""

    # computed and reported; the method's order is kept whatever the order here
    methods: tuple[str, ...] = ALL_METHODS
    # the random baseline's and the floors' draws
    seed: int = 0
    # fused qBBs a frame at most
    max_fused_boxes: int = 4096
    rrf_c: float = 60.0  # RRF's constant c (method §14; Cormack et al. 2009 use 60)
    # a registered rule's [fusion.<name>] table, built as its options dataclass
    options: dict[str, Any] = field(default_factory=dict)

    def options_of(self, fusion_rule: str) -> Any:
        """A registered rule's options: its ``[fusion.<rule>]`` table, the defaults, or None.

        None for a rule registered without options (and for every built-in rule).
        """
        if fusion_rule in self.options:
            return self.options[fusion_rule]
        return FUSION_OPTIONS[fusion_rule]() if fusion_rule in FUSION_OPTIONS else None


def check_fusion(fu: FusionConfig, where: str) -> None:
    """``[fusion]``: known methods, each once, their options."""
    c = check_value
    fusion_methods = known_fusion_methods  # method §7's and registered ones

    bad = [m for m in fu.methods if m not in fusion_methods()]
    c(
        not bad and len(fu.methods) > 0,
        where,
        "[fusion] methods",
        list(fu.methods),
        f"a non-empty list of {list(fusion_methods())}",
    )
    c(
        len(set(fu.methods)) == len(fu.methods),
        where,
        "[fusion] methods",
        list(fu.methods),
        "each method once",
    )
    c(fu.max_fused_boxes >= 1, where, "[fusion] max_fused_boxes", fu.max_fused_boxes, ">= 1")
    c(fu.rrf_c >= 0, where, "[fusion] rrf_c", fu.rrf_c, "a number >= 0")

"""One registry pattern (issue 51): every extension point is a :class:`harness.methods.Registry`."""

from __future__ import annotations

import pytest

import harness.proposals  # noqa: F401  (registers the built-in proposers, as a run does)
from harness.descriptors import REGISTRY as DESCRIPTORS
from harness.errors import ConfigError
from harness.ingest.logs import READERS
from harness.localizers.kinds import LOCALIZER_KINDS
from harness.methods import FUSION_RULES, PROPOSER_OPTIONS, PROPOSERS, Proposer, Registry
from harness.reports.tables import TABLES


def test_add_refuses_a_taken_or_reserved_name_and_the_decorator_adds() -> None:
    reg: Registry[int] = Registry("toy", reserved=("kept",))
    assert reg.add("a", 1) == 1 and reg == {"a": 1}
    with pytest.raises(
        ValueError, match=r"toy 'a' exists \(the name is taken\); known: \['a', 'kept'\]"
    ):
        reg.add("a", 2)
    with pytest.raises(ConfigError, match="toy 'kept' exists"):
        reg.add("kept", 3, ConfigError)

    @reg.entry("f")
    def f() -> int:
        return 4

    assert reg["f"] is f and f() == 4 and list(reg) == ["a", "f"]
    assert dict(reg) == {"a": 1, "f": f}  # a dict to every reader


def test_every_extension_point_is_a_registry_holding_its_built_ins() -> None:
    points = {
        "fusion rules": (FUSION_RULES, "rank_fusion"),
        "proposers": (PROPOSERS, "edges"),
        "proposers' options": (PROPOSER_OPTIONS, None),
        "localizer kinds": (LOCALIZER_KINDS, "local"),
        "log formats": (READERS, "nclt"),
        "report tables": (TABLES, None),
        "descriptors": (DESCRIPTORS, "autoencoder"),
    }
    for what, (reg, builtin) in points.items():
        assert isinstance(reg, Registry), what
        assert builtin is None or builtin in reg, what
    with pytest.raises(ValueError, match="exists"):
        PROPOSERS.add("grid5", Proposer("grid5"))  # a built-in record, as every other
    with pytest.raises(ConfigError, match="localizer kind 'name' exists"):
        LOCALIZER_KINDS.add("name", LOCALIZER_KINDS["local"], ConfigError)

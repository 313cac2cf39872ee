"""``[descriptor] precision``: what ``auto`` resolves to, and the keys it enters (issue 37)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from harness.descriptors import keys as descriptor_keys
from harness.descriptors.config import DescriptorConfig
from harness.retrieval import keys as retrieval_keys
from harness.runtime import hardware


def test_auto_is_fp32_on_every_cpu_and_bf16_only_by_name(monkeypatch) -> None:
    """Issue 50: ``auto`` never changes a table, so it is fp32 even where bf16 is native."""
    assert hardware.resolve_precision("fp32", "cpu") == "fp32"
    assert hardware.resolve_precision("bf16", "cpu") == "bf16"  # asked for: emulated if need be
    for flags in ({"avx2", "fma"}, {"avx2", "avx512f", "avx512_bf16"}, {"amx_bf16"}, set()):
        monkeypatch.setattr(hardware, "cpu_flags", lambda f=flags: frozenset(f))
        assert hardware.resolve_precision("auto", "cpu") == "fp32"
        assert hardware.resolve_precision("auto", "auto") == "fp32"


def test_this_machines_flags_are_read_from_proc_cpuinfo() -> None:
    flags = hardware.cpu_flags()
    text = Path("/proc/cpuinfo").read_text()
    assert all(f in text for f in flags) and (not flags or "fpu" in flags)


def test_fp32_keeps_the_keys_of_before_and_bf16_changes_them(monkeypatch) -> None:
    monkeypatch.setattr(hardware, "cpu_flags", lambda: frozenset({"avx2"}))
    dc = DescriptorConfig(device="cpu")
    before = {k: v for k, v in dataclasses.asdict(dc).items() if k != "precision"}
    for opts in (descriptor_keys.descriptor_options(dc), descriptor_keys.model_options(dc)):
        assert "precision" not in opts
    assert descriptor_keys.descriptor_options(dc) == {
        k: v for k, v in before.items() if k not in descriptor_keys.DESCRIPTOR_EXECUTION
    }
    bf = dataclasses.replace(dc, precision="bf16")
    assert descriptor_keys.descriptor_options(bf)["precision"] == "bf16"
    assert descriptor_keys.model_options(bf)["precision"] == "bf16"
    # auto on a CPU with AVX512-BF16 keeps the fp32 key: the same model and cache as elsewhere
    monkeypatch.setattr(hardware, "cpu_flags", lambda: frozenset({"avx512_bf16"}))
    assert descriptor_keys.descriptor_options(dc) == descriptor_keys.descriptor_options(
        dataclasses.replace(dc, precision="fp32")
    )


@pytest.mark.parametrize("value", ["fp16", "BF16", ""])
def test_a_bad_precision_is_a_config_error_naming_the_key(value: str) -> None:
    from harness.config.assemble import Overrides, with_overrides
    from harness.config.load import parse_config
    from harness.errors import ConfigError

    doc = {
        "name": "t",
        "data_root": ".",
        "sessions": [{"name": "a", "source": "x"}],
        "descriptor": {"precision": value},
    }
    with pytest.raises(ConfigError, match=r"\[descriptor\] precision"):
        with_overrides(parse_config(doc, Path("."), "t.toml"), Overrides(), "t.toml")


def test_ranking_is_bf16_only_by_name_and_its_keys_say_so(monkeypatch) -> None:
    """``auto`` ranks in fp32 even where the CPU multiplies bf16 (the exact re-measurement of
    undecided frames decides whether bf16 pays, not the machine); fp32 keeps the keys of
    before, bf16 adds to them."""
    from harness.config.schema import Config

    monkeypatch.setattr(hardware, "cpu_flags", lambda: frozenset({"avx512_bf16"}))
    assert [hardware.rank_precision(p) for p in ("auto", "fp32", "bf16")] == [
        "fp32",
        "fp32",
        "bf16",
    ]
    cfg = Config(name="t", data_root=Path("."), annotations=None, sessions=())
    plain = retrieval_keys.ranks_unit(cfg.retrieval, "a", "pk", {"a": "k"}, 0, 5)
    assert retrieval_keys.ranks_unit(cfg.retrieval, "a", "pk", {"a": "k"}, 0, 5, "fp32") == plain
    assert retrieval_keys.ranks_unit(cfg.retrieval, "a", "pk", {"a": "k"}, 0, 5, "bf16") == (
        *plain,
        {"precision": "bf16"},
    )
    assert retrieval_keys.ranks(cfg.retrieval, "pk", {"a": "k"}, "bf16")[
        :-1
    ] == retrieval_keys.ranks(cfg.retrieval, "pk", {"a": "k"})

"""The README's configuration table names every key of every table the loader reads."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from harness.config.load import _NESTED, _SECTIONS
from harness.localizers.kinds import LOCALIZER_KINDS

ROOT = Path(__file__).resolve().parents[2]


def _rows() -> dict[str, str]:
    text = (ROOT / "README.md").read_text()
    return {m[1]: m[2] for m in re.finditer(r"^\| `\[\[?([a-z_]+)\]\]?` \| (.*) \|$", text, re.M)}


def test_every_config_key_is_in_the_readme_table() -> None:
    rows = _rows()
    missing = {
        sec: [
            f.name
            for f in dataclasses.fields(cls)
            if f"`{f.name}`" not in rows.get(sec, "") and f.name != "options"
        ]
        for sec, cls in _SECTIONS.items()
    }
    assert {s: m for s, m in missing.items() if m} == {}
    # the sub-tables of [proposals] are named in its row
    for (parent, name), _ in _NESTED.items():
        assert parent != "ProposalsConfig" or f"[proposals.{name}]" in rows["proposals"], name


def test_every_localizer_kind_is_in_the_readme_table() -> None:
    row = _rows()["localizers"]
    assert all(f"`{k}" in row for k in LOCALIZER_KINDS), row

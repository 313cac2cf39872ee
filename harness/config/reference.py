"""The configuration reference, generated from the config dataclasses (``docs/config.md``).

Every table of a run's TOML is a dataclass (``harness/<stage>/config.py``); its keys are the
dataclass's fields, their defaults the fields' defaults, and what each means the comment lines
written above the field (or beside it). This module reads them back, so a new option cannot go
undocumented: ``python -m harness.config.reference --write`` writes the page,
``--check`` fails (exit 1) where the page differs from what the code says.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import sys
import typing
from pathlib import Path
from typing import Any

from harness.config.load import NESTED_TABLES, SECTIONS
from harness.config.schema import Config
from harness.ingest.config import SessionConfig
from harness.localizers.config import LocalizerConfig
from harness.localizers.kinds import LOCALIZER_KINDS
from harness.methods import FUSION_OPTIONS, PROPOSER_OPTIONS

#: Where ``--write`` puts the page, relative to the project.
PAGE = Path("docs") / "config.md"

#: The page's first line: ``--write`` replaces only a page that starts with it.
HEAD = "# Configuration reference"

_FIELD = re.compile(r"^(\s+)(\w+)\s*:\s*[^=#]+?(?:\s*=\s*(.+?))?\s*(?:#\s*(.*))?$")


def field_comments(cls: type) -> dict[str, str]:
    """Each field's comment: the ``#`` lines right above it, then any comment beside it.

    A field right under another, with no comment of its own, shares that one's comment (one
    comment above a group of fields, as ``nms_iou`` and ``max_boxes``).
    """
    lines = inspect.getsource(cls).splitlines()
    out: dict[str, str] = {}
    above: list[str] = []
    last = ""  # the comment of the field on the line before, if that line was a field
    names = {f.name for f in dataclasses.fields(cls)}
    for line in lines[1:]:
        s = line.strip()
        if s.startswith("#:") or s.startswith("# "):
            above.append(s.lstrip("#:").strip())
            last = ""
            continue
        m = _FIELD.match(line)
        if m and m.group(2) in names and m.group(2) not in out:
            beside = m.group(4) or ""
            own = " ".join([*above, beside]).replace("fmt: skip", "").strip()
            out[m.group(2)] = last = own or last
        else:
            last = ""
        above = []
    return out


_ROLE = re.compile(r":(?:mod|func|class|meth|data|attr):`~?([^`]+)`")


def _markdown(text: str) -> str:
    """Docstring text as Markdown: Sphinx roles as code spans."""
    return _ROLE.sub(r"`\1`", text)


def _summary(cls: type) -> str:
    doc = inspect.getdoc(cls) or ""
    return _markdown(" ".join(doc.split("\n\n")[0].split()))


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        v = f.default
    elif f.default_factory is not dataclasses.MISSING:
        v = f.default_factory()
        if dataclasses.is_dataclass(v):
            return "its table"
    else:
        return "required"
    if isinstance(v, str):
        return f'`"{v}"`'
    if isinstance(v, bool):
        return f"`{str(v).lower()}`"
    if isinstance(v, tuple):
        return "`[" + ", ".join(f'"{x}"' if isinstance(x, str) else str(x) for x in v) + "]`"
    if v is None:
        return "unset"
    return f"`{v}`"


def _type(hint: Any) -> str:
    text = getattr(hint, "__name__", None) if not typing.get_args(hint) else None
    return (text or str(hint).replace("typing.", "")).replace("NoneType", "None")


def table(title: str, cls: type, skip: tuple[str, ...] = ()) -> list[str]:
    """One table's section: its summary, then a row per key (type, default, meaning)."""
    hints = typing.get_type_hints(cls)
    notes = field_comments(cls)
    rows = [f"## `{title}`", "", _summary(cls), "", "| key | type | default | meaning |",
            "|---|---|---|---|"]  # fmt: skip
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        note = _markdown(notes.get(f.name, "")).replace("|", "\\|")
        rows.append(f"| `{f.name}` | {_type(hints[f.name])} | {_default(f)} | {note} |")
    return [*rows, ""]


def reference() -> str:
    """The whole page: the top-level keys, then every table and sub-table, in the load order."""
    out = [
        HEAD,
        "",
        "Generated from the config dataclasses by `python -m harness.config.reference --write`;",
        "a test fails when this page differs from the code. Every key is optional unless its",
        "default says *required*; an unknown key is one `ERROR:` line naming it. How the choices",
        "were made and measured: [Decisions](decisions.md).",
        "",
        *table("top level", Config, skip=tuple(SECTIONS) + ("import_",)),
        *table("[[sessions]]", SessionConfig),
        *table("[[localizers]]", LocalizerConfig),
    ]
    for name, kind in sorted(LOCALIZER_KINDS.items()):
        out += table(f"[[localizers]] {name} = {{...}}", kind.options)
    for section, cls in SECTIONS.items():
        out += table(f"[{section}]", cls)
        for f in dataclasses.fields(cls):
            sub = NESTED_TABLES.get((cls.__name__, f.name))
            hint = typing.get_type_hints(cls).get(f.name)
            if sub is None and isinstance(hint, type) and dataclasses.is_dataclass(hint):
                sub = hint
            if sub is not None:
                out += table(f"[{section}.{f.name}]", sub)
        registry: dict[str, type] = {"proposals": PROPOSER_OPTIONS, "fusion": FUSION_OPTIONS}.get(
            section, {}
        )
        for method, opts in sorted(registry.items()):
            if (cls.__name__, method) not in NESTED_TABLES:
                out += table(f"[{section}.{method}]", opts)
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    """``--write`` the page, or ``--check`` it (exit 1 naming the page where it is stale)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", action="store_true", help=f"write {PAGE}")
    ap.add_argument("--check", action="store_true", help=f"exit 1 where {PAGE} is stale")
    ap.add_argument("--root", type=Path, default=Path.cwd(), help="the project (default: .)")
    a = ap.parse_args(argv)
    page, text = a.root / PAGE, reference()
    if a.write:
        if page.is_file() and not page.read_text().startswith(HEAD):
            print(f"ERROR: {page} is not a page this command wrote; left as it is",
                  file=sys.stderr)  # fmt: skip
            return 1
        page.parent.mkdir(parents=True, exist_ok=True)
        page.write_text(text)
        print(f"wrote {page}")
    elif a.check:
        if not page.is_file() or page.read_text() != text:
            print(f"ERROR: {page} is stale: run python -m harness.config.reference --write",
                  file=sys.stderr)  # fmt: skip
            return 1
        print(f"{page} is what the code says")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

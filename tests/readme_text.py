"""What the README quotes, read back for the tests that compare it with a command's output."""

from __future__ import annotations

from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def table_rows_after(marker: str, tables: int = 1, path: Path = README) -> list[str]:
    """The body rows (header rows included, separator rows left out) of the ``tables`` markdown
    tables that follow ``marker`` in ``path``."""
    text = path.read_text()
    lines = text[text.index(marker) + len(marker) :].splitlines()
    rows: list[str] = []
    seen, inside = 0, False
    for line in lines:
        if line.startswith("|"):
            inside = True
            if not set(line) <= set("|-: "):
                rows.append(line)
        elif inside:
            seen, inside = seen + 1, False
            if seen == tables:
                break
    assert rows, f"no table after {marker!r} in {path.name}"
    return rows

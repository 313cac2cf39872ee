"""What the README and the manual quote, read back for the tests that compare it with output.

The manual is the README, the pages of ``docs/`` (the site ``make docs`` builds) and the
changelog: a sentence a test holds to a command's output may live on any of them, so the tests
read them as one text (:func:`manual_text`), each page separated by a blank line.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: The manual's pages: the README first, then the site's pages, then the changelog.
MANUAL = [README, *sorted((ROOT / "docs").glob("*.md")), ROOT / "CHANGELOG.md"]


def manual_text() -> str:
    """The README, every page of ``docs/`` and the changelog, as one text."""
    return "\n\n".join(p.read_text() for p in MANUAL)


def table_rows_after(marker: str, tables: int = 1, path: Path | None = None) -> list[str]:
    """The body rows (header rows included, separator rows left out) of the ``tables`` markdown
    tables that follow ``marker`` in ``path`` (the manual where None)."""
    text = path.read_text() if path is not None else manual_text()
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
    assert rows, f"no table after {marker!r} in {path.name if path else 'the manual'}"
    return rows

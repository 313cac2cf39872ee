"""The configuration reference (``docs/config.md``) is generated from the config dataclasses.

A new key cannot go undocumented: the page must be exactly what the code says (regenerate it
with ``python -m harness.config.reference --write``), and every key of every table must carry a
meaning (the comment above or beside its field).
"""

from __future__ import annotations

import dataclasses

from harness.config.load import NESTED_TABLES, SECTIONS
from harness.config.reference import PAGE, field_comments, main, reference
from harness.localizers.kinds import LOCALIZER_KINDS

from ..conftest import ROOT


def test_the_page_is_what_the_code_says() -> None:
    assert (ROOT / PAGE).read_text() == reference(), (
        "docs/config.md is stale: run python -m harness.config.reference --write"
    )


def test_every_key_of_every_table_has_a_meaning() -> None:
    page = reference()
    rows = [r for r in page.splitlines() if r.startswith("| `")]
    empty = [r for r in rows if r.rstrip().endswith("|  |")]
    assert rows and empty == []
    for section, cls in SECTIONS.items():
        assert f"## `[{section}]`" in page, section
        for f in dataclasses.fields(cls):
            assert f"| `{f.name}` |" in page, (section, f.name)
    for (parent, name), cls in NESTED_TABLES.items():
        assert field_comments(cls), (parent, name)
    for kind in LOCALIZER_KINDS:
        assert f"## `[[localizers]] {kind} = {{...}}`" in page, kind
    for table in ("[detect.null]", "[detect.keypoints]", "[detect.local]", "[proposals.segments]"):
        assert f"## `{table}`" in page, table


def test_a_comment_above_or_beside_a_field_is_its_meaning() -> None:
    @dataclasses.dataclass
    class Toy:
        # the first key
        a: int = 1
        b: int = 2  # the second, beside it
        # one comment for a group
        c: int = 3
        d: int = 4

        e: int = 5

    got = field_comments(Toy)
    group = "one comment for a group"
    assert got == {"a": "the first key", "b": "the second, beside it", "c": group, "d": group,
                   "e": ""}  # fmt: skip


def test_check_is_one_error_line_where_the_page_is_stale(tmp_path, capsys) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / PAGE).write_text("# Configuration reference\n\nan older page\n")
    assert main(["--check", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") and len(err.strip().splitlines()) == 1, err
    assert main(["--check", "--root", str(ROOT)]) == 0
    assert main(["--write", "--root", str(tmp_path)]) == 0
    assert (tmp_path / PAGE).read_text() == reference()
    # a page it did not write is left as it is
    (tmp_path / PAGE).write_text("my own notes\n")
    assert main(["--write", "--root", str(tmp_path)]) == 1
    assert capsys.readouterr().err.startswith("ERROR: ")
    assert (tmp_path / PAGE).read_text() == "my own notes\n"

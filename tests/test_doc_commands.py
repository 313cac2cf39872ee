"""Every shell block of the README and the manual (``docs/``) is run by a test, or says why not.

A command a page shows is a promise (the README's, now the site's): each command of each ``sh``
block must start with a prefix of :data:`RUN_BY`, which names the test that runs it as typed and
a string of that test's source proving it reads or types that command. A block that cannot run
here (the real NCLT logs, a Ray cluster) carries the line ``<!-- not run here: why -->`` right
above it. A new block with neither fails here, naming its page and line.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

from .conftest import ROOT

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELL = ("sh", "bash", "shell", "console")
NOT_RUN = "<!-- not run here:"

#: A command's prefix -> (the test file, the test function, a string of that function's source
#: that shows it runs the command as typed: the prefix it finds on the page, or its own words).
RUN_BY: dict[str, tuple[str, str, str]] = {
    "make reproduce-table": (
        "tests/cli/test_readme_promises.py",
        "test_make_reproduce_table_with_config_and_out",
        "reproduce-table",
    ),
    "make test": (".ci/run", "", "make test"),
    "harness inspect datasets/fixture/ros1/2012-03-31.bag": (
        "tests/cli/test_readme_paths.py",
        "test_the_readmes_robot_log_path_as_typed",
        "harness inspect datasets/fixture/",
    ),
    "harness reproduce --config datasets/fixture.toml --out results/fixture": (
        "tests/cli/test_readme_paths.py",
        "test_the_readmes_robot_log_path_as_typed",
        "harness reproduce --config datasets/fixture.toml --out results/fixture",
    ),
    "harness detect --map-images DIR --query-images DIR --out OUT": (
        "tests/pairs/test_no_poses.py",
        "test_two_image_folders_from_nothing_as_the_readme_types_it",
        'x.startswith("harness detect --map-images")',
    ),
    "harness detect --map-images DIR --query-images DIR --masks DIR --out OUT": (
        "tests/pairs/test_no_poses.py",
        "test_two_image_folders_from_nothing_as_the_readme_types_it",
        '"--masks"',
    ),
    "harness detect --map-images DIR --query-images DIR --annotations FILE --out OUT": (
        "tests/pairs/test_no_poses.py",
        "test_two_image_folders_from_nothing_as_the_readme_types_it",
        '"--annotations"',
    ),
    "harness detect --config datasets/fixture-detect.toml --map-images": (
        "tests/pairs/test_no_poses.py",
        "test_two_image_folders_from_nothing_as_the_readme_types_it",
        "harness detect --config datasets/fixture-detect.toml --map-images",
    ),
    "harness detect --config datasets/fixture-detect.toml --map 2012-01-22 --query 2012-03-31 "
    "--out results/detect-rrf": (
        "tests/detect/test_detect.py",
        "test_rerun_recording_reads_back_with_the_sdk",
        "--rerun",
    ),
    "harness detect --config datasets/fixture-detect.toml --map 2012-01-22 --query 2012-03-31 "
    "--out results/detect": ("tests/detect/test_detect.py", "detected", "fixture-detect.toml"),
    "harness detect --config datasets/fixture.toml --map 2012-01-22 --query 2012-03-31 --query "
    "2012-08-04 --out results/detect-scored": (
        "tests/detect/test_detect.py",
        "detected",
        '"2012-08-04"',
    ),
    "harness detect --config datasets/fixture.toml --map 2012-01-22 --query 2012-03-31 --query "
    "2012-08-04 --out results/detect-segments --localizer config": (
        "tests/detect/test_detect.py",
        "test_boxes_segments_with_contrast_as_typed",
        '"detect-segments"',
    ),
    "harness reproduce --config datasets/fixture-localizers.toml": (
        "tests/localizers/test_localizers.py",
        "test_the_readme_command_runs_as_typed_with_its_four_localizers",
        "harness reproduce --config datasets/fixture-localizers.toml --out",
    ),
    "harness task export --config datasets/fixture.toml --out results/byo": (
        "tests/localizers/test_byo_localizer.py",
        "exported",
        '"task", "export"',
    ),
    "python examples/hsv_localizer.py": (
        "tests/localizers/test_byo_localizer.py",
        "test_import_a_users_localizer_through_the_report_page",
        "EXAMPLE",
    ),
    "harness reproduce --config datasets/fixture.toml --out results/byo --import": (
        "tests/localizers/test_byo_localizer.py",
        "test_import_a_users_localizer_through_the_report_page",
        '"--import"',
    ),
    ".venv/bin/python examples/plugins/cdrl.py": (
        "tests/test_recipe_files.py",
        "test_four_methods_through_the_users_door_one_file_each",
        "_readme_block(SECTION",
    ),
    ".venv/bin/harness --plugin examples/plugins/cdrl.py reproduce": (
        "tests/test_recipe_files.py",
        "test_four_methods_through_the_users_door_one_file_each",
        "_readme_block(SECTION",
    ),
}


@dataclass(frozen=True)
class Block:
    """One fenced shell block: its page, first line (1-based), commands and whether it is marked."""

    page: Path
    line: int
    commands: tuple[str, ...]
    marked: str  # the reason it is not run here ("" where it is run)


def _commands(lines: list[str]) -> tuple[str, ...]:
    """The block's commands: continuation lines joined, trailing ``# comments`` dropped."""
    out: list[str] = []
    joined = ""
    for raw in lines:
        line = raw.rstrip()
        if line.endswith("\\"):
            joined += line[:-1].strip() + " "
            continue
        line = (joined + line.strip()).strip()
        joined = ""
        line = re.sub(r"\s+#\s.*$", "", line).strip()
        if line and not line.startswith("#"):
            out.append(line)
    return tuple(out)


def shell_blocks(pages: list[Path] = PAGES) -> list[Block]:
    """Every fenced ``sh`` (``bash``, ``shell``, ``console``) block of ``pages``."""
    found = []
    for page in pages:
        lines = page.read_text().splitlines()
        i = 0
        while i < len(lines):
            m = re.match(r"^\s*```(\w*)", lines[i])
            if not m:
                i += 1
                continue
            j = i + 1
            while j < len(lines) and not re.match(r"^\s*```", lines[j]):
                j += 1
            if m.group(1) in SHELL:
                above = next((x.strip() for x in reversed(lines[:i]) if x.strip()), "")
                why = (
                    above[len(NOT_RUN) :].rstrip("->").strip() if above.startswith(NOT_RUN) else ""
                )
                found.append(Block(page, i + 1, _commands(lines[i + 1 : j]), why))
            i = j + 1
    return found


def _function_source(path: Path, name: str) -> str | None:
    """The source of function ``name`` in ``path`` (a fixture's too), None where there is none."""
    text = path.read_text()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.FunctionDef) and node.name == name:
            return ast.get_source_segment(text, node)
    return None


def test_every_shell_block_is_run_by_a_test_or_marked() -> None:
    blocks = shell_blocks()
    assert len(blocks) >= 10, "the pages' shell blocks were not found"
    unrun = [
        f"{b.page.relative_to(ROOT)}:{b.line}: {c}"
        for b in blocks
        if not b.marked
        for c in b.commands
        if not any(c.startswith(prefix) for prefix in RUN_BY)
    ]
    assert unrun == [], "shell blocks no test runs (add the test to RUN_BY, or mark the block)"


def test_each_test_named_runs_what_it_is_named_for() -> None:
    """The tests of :data:`RUN_BY` exist and their source holds the command they stand for."""
    wrong = []
    for prefix, (file, name, evidence) in RUN_BY.items():
        path = ROOT / file
        src = _function_source(path, name) if name else path.read_text()
        if src is None or evidence not in src:
            wrong.append(f"{prefix!r}: {file}::{name} lacks {evidence!r}")
    assert wrong == []


def test_every_prefix_names_a_command_a_page_shows() -> None:
    """No entry outlives its command: each prefix starts some command of some page."""
    shown = [c for b in shell_blocks() for c in b.commands]
    stale = [p for p in RUN_BY if not any(c.startswith(p) for c in shown)]
    assert stale == []


def test_a_marked_block_says_why() -> None:
    marked = [b for b in shell_blocks() if b.marked]
    assert marked, "the README's NCLT command is marked as not run here"
    assert all(len(b.marked) > 10 for b in marked), [(b.page.name, b.line) for b in marked]


def test_the_readme_is_a_page_with_the_four_paths_first() -> None:
    """A README read in five minutes (issue 65): at most 250 lines, and each user path's command
    (real NCLT logs, your robot logs, two folders of images, your own localizer) in its first 120
    lines; the rest of the manual is the site."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250, len(lines)
    head = "\n".join(lines[:120])
    for command in (
        "make reproduce-table DATA=",
        "harness inspect ",
        "harness detect --map-images DIR --query-images DIR",
        "harness reproduce --config datasets/fixture.toml --out results/byo --import",
    ):
        assert command in head, command


def test_the_readmes_table_i_excerpt_is_the_fixtures() -> None:
    """The excerpt of Table I in the README is the fixture's recorded Table I (which the
    regression test holds to the suite's own run), row for row."""
    table = (ROOT / "tests" / "regression" / "table1.csv").read_text().splitlines()
    want = {row.split(",")[0]: row.split(",")[1:] for row in table}
    readme = (ROOT / "README.md").read_text()
    rows = re.findall(r"^\| (\w+)\s+\| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \| "
                      r"([0-9.]+) \|$", readme, re.M)  # fmt: skip
    assert [r[0] for r in rows] == [
        "fusion",
        "rank_fusion",
        "rank_no_fusion",
        "size_prior",
        "random",
    ]
    for name, *cells in rows:
        assert cells == want[name], name


def test_no_page_message_or_docstring_cites_a_file_outside_the_repository() -> None:
    """The method is ``docs/method.md``'s sections (``method §n``): nothing a user reads cites the
    contract this project was built from, which a clone does not hold."""
    found = []
    for path in [
        *(ROOT / "harness").rglob("*.py"),
        ROOT / "README.md",
        *(ROOT / "docs").glob("*.md"),
        *(ROOT / "datasets").glob("*.toml"),  # the configs a user copies
    ]:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"SPEC [0-9s]|shared/SPEC", line):
                found.append(f"{path.relative_to(ROOT)}:{n}")
    assert found == []
    method = (ROOT / "docs" / "method.md").read_text()
    cited = set()
    for path in (ROOT / "harness").rglob("*.py"):
        cited |= set(re.findall(r"§(\d+(?:\.\d+)?)", path.read_text()))
    missing = sorted(s for s in cited if f"### §{s} " not in method)
    assert missing == [], f"sections cited but not in docs/method.md: {missing}"

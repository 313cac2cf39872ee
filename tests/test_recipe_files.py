"""Issue 51's recipe test: four methods added through the users' door, and the files each took.

A fusion rule with an option, a proposer with an option, a localizer kind that caches and a log
format are each one Python file of the user's, handed to the harness as a plugin (``plugins`` in
the config, ``--plugin`` on the command line) and run as a user types the command; each must take
effect and the harness's own tree must be untouched (the user's count: one file each). The same
four added as the harness's own, by the recipes of ``docs/architecture.md`` (*Where to add*), are
applied to a copy of the package and imported there: the count is the files of the copy that
differ from the package (at most two each).
"""

from __future__ import annotations

import ast
import filecmp
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from .readme_text import manual_text

ROOT = Path(__file__).resolve().parents[1]

#: The user's four files: each is all a user writes to add the method.
#: The user's four files (``examples/plugins/``, the README's): each is all a user writes to add
#: the method.
PLUGINS = ROOT / "examples" / "plugins"
USER_FILES = ("kth_rank.py", "centre.py", "colour.py", "cdrl.py")


def _readme_block(after: str, fence: str) -> str:
    """The first fenced block of language ``fence`` after the heading ``after`` in the README."""
    text = manual_text()
    blocks = re.findall(r"^```(\w*)\n(.*?)^```", text[text.index(after) :], re.S | re.M)
    return next(body for lang, body in blocks if lang == fence)


def _mine_toml() -> str:
    """The README's ``mine.toml``: the fixture's config with the README's lines put in."""
    chunks = _readme_block(SECTION, "toml").strip().split("\n\n")
    plugins, session, proposals = chunks[0], chunks[1], "\n\n".join(chunks[2:4])
    rest = "\n\n".join(chunks[4:])
    source = next(ln for ln in session.splitlines() if ln.startswith("source = "))
    text = (ROOT / "datasets" / "fixture.toml").read_text()
    for old, new in (
        ('name = "fixture"\n', f'name = "fixture"\n{plugins}\n'),
        ('source = "{data_root}/ros2/2012-08-04"', source),
        ('[proposals]\nmethods = ["grid5", "edges"]\n', proposals + "\n"),
    ):
        assert old in text, old
        text = text.replace(old, new)
    return text + "\n" + rest + "\n"


#: The README's section that shows the plugins at work.
SECTION = "## Add a method of your own: plugins"


def _package_state() -> dict[str, float]:
    return {str(p): p.stat().st_mtime for p in (ROOT / "harness").rglob("*.py")}


def test_four_methods_through_the_users_door_one_file_each(
    local_run: tuple, default_world: Path, tmp_path: Path
) -> None:
    """The README's worked example, its two commands as typed (the project laid out in
    ``tmp_path``: the examples, the fixture world as ``datasets/fixture``, the annotations)."""
    (tmp_path / "datasets").mkdir()
    (tmp_path / "datasets" / "fixture").symlink_to(default_world)
    for name in ("examples", "annotations"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / "mine.toml").write_text(_mine_toml())
    _, _, done = local_run  # the fixture run's cache: the sessions the toys leave alone are reused
    out = tmp_path / "results" / "mine"
    shutil.copytree(done / "cache", out / "cache")
    shutil.copy(done / ".dbl-harness.json", out / ".dbl-harness.json")
    before = _package_state()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for line in _readme_block(SECTION, "sh").strip().splitlines():
        argv = line.split()
        exe = (
            [sys.executable, "-m", "harness.cli"]
            if argv[0].endswith("harness")
            else [sys.executable]
        )
        res = subprocess.run(
            [*exe, *argv[1:]], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=900
        )
        assert res.returncode == 0, (line, res.stderr[-3000:])
    # the user's count: one file per method, and not one file of the harness touched
    assert _package_state() == before
    rec = json.loads((out / "run.json").read_text())
    assert sorted(Path(p["path"]).name for p in rec["plugins"]) == sorted(USER_FILES)
    assert all(Path(p["path"]).parent == PLUGINS for p in rec["plugins"])  # one file each
    assert rec["localizers"] == [{"name": "rgb-hist", "kind": "colour"}]
    # the log format: the session read from the toy file, as many frames as from the bag
    assert rec["ingest"]["2012-08-04"]["format"] == "cdrl"
    assert rec["ingest"]["2012-08-04"]["frames_written"] == 64
    # the localizer kind: its cached histograms, 4^3 bins, of every session it ranked
    entries = sorted((out / "cache" / "colour").iterdir())
    assert len(entries) >= 2 and np.load(entries[0] / "desc.npy").shape[1] == 64
    # the proposer and its option: one central box of half the frame per frame, ranked
    ranks = pd.read_parquet(out / "ranks.parquet")
    cen = ranks[ranks["proposal_method"] == "centre"]
    assert len(cen) and np.allclose(cen[["x1", "y1", "x2", "y2"]].iloc[0], [30, 40, 90, 120])
    # the fusion rule and its option: listed after SPEC's, and one sample's LoC by hand
    t1 = pd.read_csv(out / "table1.csv")
    assert t1["fusion"].tolist() == ["rank_fusion", "kth_rank"]
    assert "k-th best rank" in (out / "table1.md").read_text()
    assert "k-th best rank" in (out / "report.html").read_text()  # through to the last output
    s = pd.read_parquet(out / "cache" / "samples" / rec["keys"]["samples"] / "samples.parquet")
    s = s[(s["proposal_method"] == "all") & (s["N"] >= 3)].iloc[0]
    img = ranks[
        (ranks["q_session"] == s.q_session)
        & (ranks["q_utime"] == s.q_utime)
        & (ranks["r_session"] == s.r_session)
    ]
    covers = (img["x1"] <= s.x1) & (img["y1"] <= s.y1) & (img["x2"] >= s.x2) & (img["y2"] >= s.y2)
    inv = sorted((int(L) / (int(L) + 1 - int(k)) for k, L in img.loc[covers, ["rank", "L"]].values))
    assert covers.sum() == s.N and np.isclose(s.loc_kth_rank, inv[-3])  # k = 3, not the default


def _example(name: str, *defs: str) -> str:
    """The source of the top-level definitions ``defs`` of ``examples/plugins/<name>``: a
    built-in is the user's code, put where the harness keeps its own, with the registration the
    harness uses there (written once, in the example)."""
    src = (PLUGINS / name).read_text()
    lines = src.splitlines(keepends=True)
    spans = {}
    for n in ast.parse(src).body:
        if isinstance(n, ast.ClassDef | ast.FunctionDef):
            start = min([d.lineno for d in n.decorator_list] + [n.lineno])
            spans[n.name] = (start, n.end_lineno)
        elif isinstance(n, ast.Assign) and isinstance(n.targets[0], ast.Name):
            spans[n.targets[0].id] = (n.lineno, n.end_lineno)
    return "".join("\n\n" + "".join(lines[spans[d][0] - 1 : spans[d][1]]) for d in defs)


#: The harness's own recipe for each method (docs/architecture.md, *Where to add*): the files of
#: the package it edits, each edit an (anchor, text put after it) or a whole new file.
BUILTIN_EDITS: dict[str, dict[str, list[tuple[str, str]] | str]] = {
    "fusion rule with an option": {
        "methods.py": [
            (
                '    _builtin("random", "random", kind="image", baseline=True),\n',
                '    _builtin("kth_rank", "k-th best rank", options=("options",), **_RANK),\n',
            )
        ],
        "fusion/rules/kth_rank.py": (
            '"""The k-th best rank."""\n\nfrom dataclasses import dataclass\n\n'
            "import numpy as np\n\nfrom harness.fusion.rules.base import rule\n"
            "from harness.methods import FUSION_OPTIONS\n"
            + _example("kth_rank.py", "KthRank", "kth_rank")
            + '\n\nFUSION_OPTIONS.add("kth_rank", KthRank)\nrule("kth_rank")(kth_rank)\n'
        ),
    },
    "proposer with an option": {
        "methods.py": [('    Proposer("segments"),\n', '    Proposer("centre"),\n')],
        "proposals/builtin.py": [
            ("", _example("centre.py", "Centre", "centre")),
            ("", '\n\nPROPOSER_OPTIONS.add("centre", Centre)\nproposer("centre")(centre)\n'),
            ("from __future__ import annotations\n", "from dataclasses import dataclass\n"),
            ("from harness.methods import proposer", ", PROPOSER_OPTIONS"),
        ],
    },
    "localizer kind that caches": {
        "localizers/kinds/colour.py": (
            '"""RGB histograms."""\n\nfrom dataclasses import dataclass\n'
            "from functools import partial\n\nimport cv2\nimport numpy as np\n\n"
            "from harness.imagestore import read_image\n"
            "from harness.localizers.kinds.base import LocalizerKind\n"
            "from harness.records import FRAME_KEY\n"
            "from harness.runtime.cache import write_parquet\n"
            + _example("colour.py", "Colour", "describe", "colour_ranks")
            + '\n\nKIND = LocalizerKind("colour", Colour, ranks=colour_ranks)\n'
        ),
        "localizers/kinds/__init__.py": [
            ("import bovw, descriptor, imported, keypoints, local", ", colour"),
            ("(descriptor, bovw, imported, local, keypoints", ", colour"),
        ],
    },
    "log format": {
        "ingest/cdrl_log.py": '"""JSON lines of CDR messages (examples/plugins/cdrl.py)."""\n\n'
        "import base64\nimport json\n\nfrom rosbags.typesys import Stores, get_typestore\n\n"
        "from harness.ingest.log_types import Message\n" + _example("cdrl.py", "STORE", "CdrLines"),
        "ingest/logs.py": [
            (
                "from harness.ingest.rosbags_log import RosbagsLog\n",
                "from harness.ingest.cdrl_log import CdrLines\n",
            ),
            (
                '    READERS.add("nclt", nclt)\n',
                '    READERS.add("cdrl", LogFormat("cdrl", CdrLines()))\n',
            ),
        ],
    },
}

#: What the copy must then hold, checked in a fresh interpreter that imports it.
BUILTIN_CHECK = """
import numpy as np
from pathlib import Path
from harness.fusion.fuse import loc_from_cover
from harness.fusion.config import FusionConfig
from harness.ingest.logs import detect_format
from harness.localizers.kinds import LOCALIZER_KINDS
from harness.proposals.config import ProposalsConfig
from harness.methods import PROPOSERS
from harness.proposals import proposers  # attaches the built-in proposers' functions
cover = np.array([[1, 1, 1], [1, 0, 0]], bool)
r, L = np.array([0.1, 0.5, 0.9]), np.full(3, 10.0)
opts = FusionConfig().options_of("kth_rank")
got = loc_from_cover(cover, "kth_rank", r=r, d=np.ones(3), L=L, options=type(opts)(k=2))
assert opts.k == 2 and np.allclose(got, [10 / 6, 0.0]), got
boxes, _ = PROPOSERS["centre"].run(np.zeros((8, 8, 3), np.uint8), ProposalsConfig())
assert np.allclose(boxes, [[3, 3, 5, 5]]), boxes
assert LOCALIZER_KINDS["colour"].ranks is not None
Path("x.cdrl").write_text("")
assert detect_format(Path("x.cdrl")) == "cdrl"
print("ok")
"""


def _apply(pkg: Path, edits: dict[str, list[tuple[str, str]] | str]) -> None:
    """One recipe's edits, in the copy of the package: text after an anchor ('' : at the end)."""
    for rel, edit in edits.items():
        path = pkg / rel
        if isinstance(edit, str):
            path.write_text(edit)
            continue
        text = path.read_text()
        for anchor, add in edit:
            if not add:
                continue
            if not anchor:
                text += add
                continue
            assert anchor in text, f"{rel}: the recipe's anchor {anchor!r} moved"
            text = text.replace(anchor, anchor + add, 1)
        path.write_text(text)


def _changed(pkg: Path) -> set[str]:
    """The files of the copy that differ from the package, or are new."""
    out = set()
    for f in pkg.rglob("*.py"):
        orig = ROOT / "harness" / f.relative_to(pkg)
        if not orig.exists() or not filecmp.cmp(f, orig, shallow=False):
            out.add(str(f.relative_to(pkg)))
    return out


def _copy(dest: Path) -> Path:
    pkg = dest / "harness"
    shutil.copytree(ROOT / "harness", pkg, ignore=shutil.ignore_patterns("__pycache__"))
    return pkg


def test_the_harness_own_recipes_touch_at_most_two_files_each(tmp_path: Path) -> None:
    counts = {}
    for i, (what, edits) in enumerate(BUILTIN_EDITS.items()):
        alone = _copy(tmp_path / f"alone{i}")  # each recipe on a copy of its own, counted
        _apply(alone, edits)
        counts[what] = len(_changed(alone))
    pkg = _copy(tmp_path / "copy")  # all four on one copy, imported and tried
    for edits in BUILTIN_EDITS.values():
        _apply(pkg, edits)
    res = subprocess.run(
        [sys.executable, "-c", BUILTIN_CHECK],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(pkg.parent)},
        timeout=300,
    )
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr[-3000:]
    assert counts == dict.fromkeys(BUILTIN_EDITS, 2), counts

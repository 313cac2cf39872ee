"""The package's layout: no import circle among ``harness`` modules, lazy imports included.

The import graph is built with ``ast`` from every ``import`` statement anywhere in a module
(function-level ones too); importing ``a.b.c`` also imports the packages ``a`` and ``a.b``. A cycle
is a strongly connected component of more than one module, named in the failure.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

from .conftest import ROOT

PACKAGE = ROOT / "harness"


def _modules() -> dict[str, Path]:
    mods = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = f.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        mods[name] = f
    return mods


def import_graph() -> dict[str, set[str]]:
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, f in mods.items():
        pkg = m if f.name == "__init__.py" else m.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(f.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                targets = [
                    f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names
                ]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            for t in targets:
                parts = t.split(".")
                for k in range(2, len(parts) + 1):  # importing a.b.c runs a.b's __init__ too
                    u = ".".join(parts[:k])
                    if u in mods and u != m and not m.startswith(u + "."):
                        graph[m].add(u)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_detector_finds_a_circle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_circle_among_harness_modules() -> None:
    graph = import_graph()
    assert "harness.methods" in graph and not graph["harness.methods"]  # the bottom of the house
    assert "harness.proposals.config" in graph["harness.config.schema"]
    assert cycles(graph) == []


#: The layers, lowest first . A module may import its own layer and the layers below,
#: never one above: data flows up this list, and evaluation never imports presentation.
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "harness",
        "harness.errors",
        "harness.records",
        "harness.methods",
        "harness.inputs",
        "harness.checks",
        "harness.boxes",
    ),
    ("harness.runtime", "harness.imagestore", "harness.perturb", "harness.features"),
    ("harness.ingest",),
    ("harness.fixture", "harness.pairs"),
    ("harness.proposals",),
    ("harness.descriptors",),
    ("harness.retrieval",),
    ("harness.evaluate",),
    ("harness.fusion",),
    ("harness.localizers",),
    # the change detector's stage: registration, the plain difference, boxes, the no-change
    # null, calibration, with its config section and presets
    ("harness.detect",),
    # the root config assembles every stage's section (``harness/<stage>/config.py``)
    ("harness.config",),
    ("harness.reports",),
    ("harness.pipeline",),
    # the applications: ``reproduce`` and ``detect`` run the chain and hand on a typed result
    ("harness.apps",),
    ("harness.cli",),
)


def layer_of(module: str) -> int:
    """The layer of ``module``: that of the longest prefix named in :data:`LAYERS`."""
    best, at = -1, -1
    for i, names in enumerate(LAYERS):
        for n in names:
            if (module == n or module.startswith(n + ".")) and len(n) > best:
                best, at = len(n), i
    assert at >= 0, f"{module} is in no layer: add it to LAYERS"
    return at


def test_no_import_goes_up_a_layer() -> None:
    """No import reaches a layer above; a package whose ``__init__`` imports nothing of the
    harness (``harness.detect``, entered on the way to its config section) carries nothing up."""
    graph = import_graph()
    mods = _modules()
    empty = {m for m, f in mods.items() if f.name == "__init__.py" and not graph[m]}
    upward = [
        f"{m} (layer {layer_of(m)}) imports {t} (layer {layer_of(t)})"
        for m, targets in graph.items()
        for t in sorted(targets - empty)
        if layer_of(t) > layer_of(m)
    ]
    assert upward == []


def test_few_top_level_modules() -> None:
    """The top of ``harness/`` keeps only what every layer imports; the rest are packages."""
    top = sorted(p.stem for p in PACKAGE.glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 10, top


def _imports(f: Path) -> list[ast.ImportFrom]:
    return [n for n in ast.walk(ast.parse(f.read_text())) if isinstance(n, ast.ImportFrom)]


def test_the_pipeline_makes_no_key() -> None:
    """Each stage's cache key is made in its package (``harness/<stage>/keys.py``): the
    modules that compose the stages hash nothing of their own."""
    makers = [
        str(f.relative_to(ROOT))
        for f in sorted((PACKAGE / "pipeline").glob("*.py"))
        if "stable_hash" in f.read_text() or "content_sha(" in f.read_text()
    ]
    assert makers == ["harness/pipeline/context.py"], makers  # a localizer's file, for run.json


def test_stage_functions_live_in_their_packages() -> None:
    """A cache entry is built by its stage's function (``harness/<stage>/stage.py``):
    the pipeline hands each its sections of the config and builds none itself."""
    builders = [
        f"{f.relative_to(ROOT)}: {call}"
        for f in sorted((PACKAGE / "pipeline").glob("*.py"))
        if f.name != "context.py"  # the run, which the stage functions build their entries in
        for call in ("p.unit(", "p.units(", "p.sharded(")
        if call in f.read_text()
    ]
    assert builders == []
    homes = {f.parent.name for f in PACKAGE.glob("*/stage.py")}
    assert homes >= {"ingest", "pairs", "proposals", "descriptors", "retrieval", "fusion"}, homes


def test_no_module_imports_a_private_name_of_another() -> None:
    private = [
        f"{f.relative_to(ROOT)}: from {n.module} import {a.name}"
        for f in _modules().values()
        for n in _imports(f)
        if (n.module or "").startswith("harness") or n.level
        for a in n.names
        if a.name.startswith("_") and not a.name.startswith("__")
    ]
    assert private == []


def test_no_module_re_exports_beyond_its_package() -> None:
    """``__all__`` of a plain module names only what it defines; ``import x as x`` is not used.

    A package's ``__init__`` may gather its own submodules' API (``harness.ingest``,
    ``harness.retrieval``, ...), never another package's.
    """
    bad = []
    for name, f in _modules().items():
        tree = ast.parse(f.read_text())
        imported: dict[str, str] = {}
        for n in tree.body:
            if isinstance(n, ast.ImportFrom):
                for a in n.names:
                    if a.asname and a.asname == a.name:
                        bad.append(f"{name}: import {a.name} as {a.name}")
                    imported[a.asname or a.name] = n.module or ""
        for n in tree.body:
            if isinstance(n, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "__all__" for t in n.targets
            ):
                for e in ast.literal_eval(n.value):
                    src = imported.get(e)
                    if src is None:
                        continue
                    if f.name != "__init__.py" or not src.startswith(name + "."):
                        bad.append(f"{name}: __all__ re-exports {e} from {src}")
    assert bad == []


#: The longest a function of the package may be : a longer one is cut into named steps.
MAX_FUNCTION_LINES = 80


def test_no_function_is_longer_than_80_lines() -> None:
    long = []
    for name, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{name}.{node.name} ({n} lines, line {node.lineno})")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


#: Tests of the whole project rather than of one package: they stay at the top of ``tests/``.
PROJECT_TESTS = frozenset(
    {
        "test_layout",
        "test_recipes",
        "test_recipe_files",
        "test_doc_figures",
        "test_bench_command",
        "test_gpu",
        "test_bad_input",
        "test_lock",
        "test_install",
        "test_tools",
        "test_doc_commands",
        "test_user_text",
    }
)


def test_tests_mirror_the_packages() -> None:
    """A package's tests live in ``tests/<package>/`` , so the tree of the tests is the
    tree of the code; only the project-wide ones sit at the top."""
    tests = ROOT / "tests"
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    packages |= {p.stem for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    misplaced = []
    for f in sorted(tests.rglob("test_*.py")):
        rel = f.relative_to(tests)
        top = len(rel.parts) == 1 and f.stem in PROJECT_TESTS
        nested = len(rel.parts) == 2 and rel.parts[0] in packages
        if not (top or nested):
            misplaced.append(str(rel))
    assert misplaced == []
    dirs = {d.name for d in tests.iterdir() if (d / "__init__.py").is_file()}
    assert dirs <= packages and {"detect", "pipeline", "ingest"} <= dirs


def test_no_assert_checks_a_value_in_the_package() -> None:
    """Checks are errors that say what is wrong : ``python -O`` drops an ``assert``, and
    an ``AssertionError`` names no file, row or option."""
    found = [
        f"{path.relative_to(ROOT)}:{node.lineno}"
        for path in _modules().values()
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Assert)
    ]
    assert found == []


def test_no_parameter_is_named_method() -> None:
    """One vocabulary : a proposal method is a ``proposer``, a fusion method a
    ``fusion_rule``; a parameter named ``method`` said one in some functions and the other in
    the rest."""
    found = [
        f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"
        for path in _modules().values()
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and "method"
        in [a.arg for a in [*node.args.posonlyargs, *node.args.args, *node.args.kwonlyargs]]
    ]
    assert found == []


#: The libraries a function may import where it needs them , each for a reason: heavy to
#: import where most commands never use them (torch, faiss, scipy's submodules, matplotlib,
#: pycocotools), optional extras (ray, rerun) or the readers of one log format (mcap, lz4,
#: rosbags), and rich for one console table. Every other import, the package's own above all,
#: sits at the top of its module, where a reader sees what the module depends on.
LAZY_IMPORTS = frozenset(
    {"torch", "faiss", "scipy", "matplotlib", "pycocotools", "ray", "rerun", "mcap", "lz4",
     "rosbags", "rich"}
)  # fmt: skip


def test_function_level_imports_are_the_justified_ones() -> None:
    found = []
    for name, path in _modules().items():
        if name.startswith("harness.cli"):  # the commands import their stage where they run it
            continue
        for fn in ast.walk(ast.parse(path.read_text())):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.ImportFrom):
                    tops = [("." if node.level else "") + (node.module or "").split(".")[0]]
                elif isinstance(node, ast.Import):
                    tops = [a.name.split(".")[0] for a in node.names]
                else:
                    continue
                found += [f"{name}.{fn.name}: {t}" for t in tops if t not in LAZY_IMPORTS]
    assert found == []


#: The longest a module may be: one idea may take up to 500 lines; a module cut where two ideas
#: meet, never to meet a count.
MAX_MODULE_LINES = 500


def test_no_module_over_500_lines() -> None:
    over = sorted(
        f"{name} ({n} lines)"
        for name, path in _modules().items()
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    )
    assert over == [], "cut them by job"


def _parameter_count(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = fn.args
    names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    n = len(names) + (a.vararg is not None) + (a.kwarg is not None)
    return n - (bool(names) and names[0] in ("self", "cls"))


def test_no_function_takes_nine_or_more_parameters() -> None:
    """A long parameter list is grouped into a record (``DetectRun``, ``RankSettings``,
    ``Engine``, ``ChanceSettings`` ...)."""
    many = {
        f"{name}.{fn.name}"
        for name, path in _modules().items()
        for fn in ast.walk(ast.parse(path.read_text()))
        if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef) and _parameter_count(fn) >= 9
    }
    assert not many, sorted(many)


#: What a renderer of ``harness.reports`` may take from the layers that compute (issue 51:
#: evaluate computes, reports render): words, marks and constants, and the LoC map's drawing.
#: ``harness.reports.write`` alone calls the computations, to write their results to files first.
RENDER_IMPORTS = frozenset(
    {
        "MARK_LEGEND",
        "VERDICT_MARKS",
        "VERDICT_WORDS",
        "VERDICT_TEX",
        "MIN_POSITIVE_IMAGES",
        "few_text",
        "few_warning",
        "CLEAN_ROC",
        "AP_COLUMNS",
        "loc_map",
    }
)


#: What ``reports/write.py`` asks of ``evaluate/``: each returns rows a report writes as they are.
WRITE_ASKS = frozenset(
    {
        "sample_groups",
        "leaderboard",
        "localization_stats",
        "pixel_image_rows",
        "page_breakdowns",
        "split_report",
        "Split",
        "paper_splits",
        "confound_warnings",
        "holm_columns",
    }
)


def test_the_reports_writer_asks_evaluate_for_its_rows() -> None:
    """``reports/write.py`` orders the evaluation : one call of ``evaluate/`` per figure
    it writes, the split reports' rows among them (``evaluate.split_reports``), and none of the
    APs, labels or curves computed in it."""
    asks = {
        a.name
        for node in _imports(PACKAGE / "reports" / "write.py")
        if (node.module or "").startswith("harness.evaluate")
        for a in node.names
    }
    assert asks == WRITE_ASKS, sorted(asks ^ WRITE_ASKS)


def test_reports_render_what_evaluate_computed() -> None:
    computing = ("harness.evaluate", "harness.fusion")
    found = [
        f"{name}: {node.module}.{a.name}"
        for name, path in _modules().items()
        if name.startswith("harness.reports") and name != "harness.reports.write"
        for node in _imports(path)
        if (node.module or "").startswith(computing)
        for a in node.names
        if a.name not in RENDER_IMPORTS
    ]
    assert found == []


def test_the_detect_chunk_reaches_no_labelling() -> None:
    """``harness detect``'s chunk fuses ranks unlabelled: nothing it imports, however indirectly,
    is the evaluation's labelling (RoC/SoB, splits) or the annotation reader the benchmark's
    samples are labelled from."""
    graph = import_graph()
    seen, todo = set(), ["harness.detect.chunk"]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph.get(m, ()))
    assert "harness.fusion.samples" in seen  # the fusion itself is shared
    assert not seen & {"harness.evaluate.splits", "harness.ingest.annotations"}, sorted(seen)

"""Benchmark cases, one module each (``bench/cases/<name>.py`` defines ``case_<name>(quick)``).

``python -m bench.cases NAME [--quick]`` runs one case and prints one JSON line per result;
``python -m bench`` runs each in its own subprocess (bench/__main__.py). A new case is a module
here and a line in :data:`CASES`.
"""

from __future__ import annotations

import importlib

#: Case name (as ``--only`` takes it) -> its module, in the order ``python -m bench`` runs them.
CASES = {
    "ingest": "ingest",
    "crops": "crops",
    "descriptor": "descriptor",
    "ranking": "ranking",
    "localizers": "localizers",
    "detect": "detect",
    "fusion": "fusion",
    "executor": "executor",
    "e2e": "e2e",
    "full-nclt": "full_nclt",
    "fixture-figures": "fixture_figures",
}


#: Case name -> the code it measures (paths for ``git log``): a row is stale once a later commit
#: touches one of them (``bench/provenance.py``).
MEASURES: dict[str, tuple[str, ...]] = {
    "ingest": ("harness/ingest", "bench/cases/ingest.py"),
    "crops": ("harness/crops.py", "harness/imagestore.py", "bench/cases/crops.py"),
    "descriptor": ("harness/descriptors", "bench/cases/descriptor.py"),
    "ranking": ("harness/retrieval", "bench/cases/ranking.py"),
    "localizers": ("harness", "bench/cases/localizers.py", "bench/nclt_localizers.toml"),
    "detect": ("harness", "bench/cases/detect.py", "bench/nclt_detect.toml"),
    "fusion": (
        "harness/fusion.py",
        "harness/metrics.py",
        "harness/splits.py",
        "harness/reports.py",
        "bench/cases/fusion.py",
    ),
    "executor": ("harness/executors.py", "harness/cache.py", "bench/cases/executor.py"),
    "e2e": ("harness", "bench/cases/e2e.py", "bench/nclt_scale.toml"),
    "full-nclt": ("harness", "bench/cases/full_nclt.py", "bench/nclt_full.toml"),
    "fixture-figures": (
        "harness",
        "bench/cases/fixture_figures.py",
        "datasets/fixture.toml",
        "annotations",
    ),
}


def run(name: str, quick: bool) -> None:
    """Run case ``name``: its module's ``case_<module>(quick)``."""
    module = CASES[name]
    getattr(importlib.import_module(f"{__name__}.{module}"), f"case_{module}")(quick)

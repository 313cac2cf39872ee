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
}


def run(name: str, quick: bool) -> None:
    """Run case ``name``: its module's ``case_<module>(quick)``."""
    module = CASES[name]
    getattr(importlib.import_module(f"{__name__}.{module}"), f"case_{module}")(quick)

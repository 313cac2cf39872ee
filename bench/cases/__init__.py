"""Benchmark cases, one module each (``bench/cases/<name>.py`` defines ``case_<name>(quick)``).

``python -m bench.cases NAME [--quick]`` runs one case and prints one JSON line per result;
``python -m bench`` runs each in its own subprocess (bench/__main__.py). A new case is a module
here and a line in :data:`CASES`.
"""

from __future__ import annotations

import importlib

#: Case name (as ``--only`` takes it) -> (its module, the code it measures beyond that module), in
#: the order ``python -m bench`` runs them. A row is stale once a later commit touches one of the
#: measured paths (``bench/provenance.py``).
CASES: dict[str, tuple[str, tuple[str, ...]]] = {
    "ingest": ("ingest", ("harness/ingest",)),
    "crops": (
        "crops",
        (
            "harness/descriptors/crops.py",
            "harness/imagestore.py",
            "harness/proposals/proposers.py",
            "harness/proposals/builtin.py",
        ),
    ),
    "descriptor": ("descriptor", ("harness/descriptors",)),
    "training": ("training", ("harness/descriptors/autoencoder.py",)),
    "ranking": ("ranking", ("harness/retrieval",)),
    "localizers": ("localizers", ("harness", "bench/nclt_localizers.toml")),
    "detect": ("detect", ("harness", "bench/nclt_detect.toml")),
    "local": (
        "local",
        ("harness/localizers/local.py", "harness/localizers/align.py", "harness/imagestore.py"),
    ),
    "keypoints": (
        "keypoints",
        (
            "harness/localizers/keypoints.py",
            "harness/localizers/local.py",
            "harness/detect/difference.py",
            "harness/proposals/builtin.py",
        ),
    ),
    "folders": ("folders", ("harness",)),
    "real-detect": ("real_detect", ("harness",)),
    "fusion": (
        "fusion",
        (
            "harness/fusion/fuse.py",
            "harness/fusion/samples.py",
            "harness/evaluate/metrics.py",
            "harness/evaluate/splits.py",
            "harness/evaluate/aps.py",
            "harness/evaluate/pixel_aps.py",
            "harness/proposals/builtin.py",
        ),
    ),
    "executor": ("executor", ("harness/runtime/executors.py", "harness/runtime/cache.py")),
    "e2e": ("e2e", ("harness", "bench/nclt_scale.toml")),
    "full-nclt": (
        "full_nclt",
        (
            "harness",
            "bench/nclt_full.toml",
            "bench/cases/kernel_levels.py",
            "bench/cases/nclt_sessions.py",
        ),
    ),
    "precision": ("precision", ("harness", "bench/nclt_scale.toml")),
    "fixture-figures": ("fixture_figures", ("harness", "datasets/fixture.toml", "annotations")),
}


def measures(name: str) -> tuple[str, ...]:
    """The paths case ``name`` measures: its own module and the code listed in :data:`CASES`."""
    module, paths = CASES.get(name, ("", ("harness",)))
    return (*paths, f"bench/cases/{module}.py") if module else paths


def run(name: str, quick: bool) -> None:
    """Run case ``name``: its module's ``case_<module>(quick)``."""
    module = CASES[name][0]
    getattr(importlib.import_module(f"{__name__}.{module}"), f"case_{module}")(quick)

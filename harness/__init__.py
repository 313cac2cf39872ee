"""dbl-harness: a batch benchmark of self-localization as change detection on NCLT logs.

The pipeline's chain is :mod:`harness.pipeline.chain`; what it computes is ``docs/method.md``
(its sections are what ``method §n`` cites) and the stage map ``docs/architecture.md``.
"""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _v

from harness import kernels

# before anything imports numpy, torch, OpenCV or faiss: the same kernels on every CPU of the kind
kernels.LOADED_BEFORE[:] = kernels.pin()

__all__ = ["__version__"]
try:
    __version__ = _v("dbl-harness")
except PackageNotFoundError:  # pragma: no cover - not installed
    __version__ = "0.0.0"

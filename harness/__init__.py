from importlib.metadata import version as _v

__all__ = ["__version__"]
try:
    __version__ = _v("dbl-harness")
except Exception:  # pragma: no cover - not installed
    __version__ = "0.0.0"

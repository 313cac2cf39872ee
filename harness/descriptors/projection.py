"""Compact descriptors: a PCA (or PCA-whitening) projection learned on the reference sessions.

method §6 ranks with the full descriptor (16,384 dims for the paper's autoencoder); at the
scale of the whole NCLT that is 52 GB of float16 descriptors and hours of ranking. With
``[projection] dim > 0`` (``docs/method.md``) the projection is fitted before any descriptor is
stored, on a seeded sample of ``fit_samples`` reference-session subimages streamed through the
encoder (:func:`harness.descriptors.extract.fit_projection_unit`), and every descriptor shard
is projected as it is encoded: only ``dim`` float16 values per subimage ever reach the disk.

The fit: the sample's mean; the principal directions are the eigenvectors of the sample's
covariance, from the smaller of its two Gram forms (``n x n`` when ``n < D``, else ``D x D``)
with LAPACK's ``syevr`` for the top ``dim`` only (deterministic; each direction's sign is fixed so
that its largest
coordinate is positive). Applying it centres, rotates onto the top ``dim`` directions,
optionally divides each by its standard deviation (whitening), and L2-normalises again, so
descriptors stay unit vectors as method §6 asks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from harness.descriptors.base import normalize
from harness.descriptors.config import ProjectionConfig
from harness.errors import ConfigError

#: Variance floor for whitening, relative to the largest component's variance.
WHITEN_EPS = 1e-6


def _top_eigh(sym: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` largest eigenvalues (descending) of a symmetric matrix and their eigenvectors.

    Only those eigenvectors are computed (LAPACK ``syevr`` through scipy), which is what makes
    an 8,192-row fit take seconds rather than minutes.
    """
    from scipy.linalg import eigh

    m = len(sym)
    w, v = eigh(sym, subset_by_index=[m - k, m - 1], driver="evr")
    return w[::-1], v[:, ::-1]


def fit_projection(pc: ProjectionConfig, sample: np.ndarray, tmp: Path) -> dict[str, Any]:
    """Fit the projection on ``sample`` (n, D) and save it into ``tmp``.

    Args:
        pc: ``[projection]`` (``dim``, ``whiten``).
        sample: Reference descriptors (L2-normalised rows); centred here in place.
        tmp: The entry's directory: ``mean.npy`` (D,), ``components.npy`` (D, dim) and
            ``scale.npy`` (dim,) (ones without whitening), all float32.

    Returns:
        ``{"fitted_on", "input_dim", "dim", "explained_variance"}`` (the share of the sample's
        variance the kept directions hold).

    Raises:
        ConfigError: ``dim`` exceeds the input dimension or the number of sampled rows.
    """
    n, D = sample.shape
    if pc.dim > min(D, n):
        raise ConfigError(
            f"[projection] dim = {pc.dim} exceeds min(input dim {D}, sampled reference rows {n})"
        )
    mean = sample.mean(0, dtype=np.float64)
    sample -= mean.astype(sample.dtype)
    if n < D:  # eigenvectors of X X^T (n x n) map to the covariance's through X^T
        w, u = _top_eigh(np.asarray(sample @ sample.T, np.float64), pc.dim)
        comp = np.asarray(sample.T @ u.astype(sample.dtype), np.float64) / np.sqrt(
            np.maximum(w, np.finfo(np.float64).tiny)
        )
    else:
        w, comp = _top_eigh(np.asarray(sample.T @ sample, np.float64), pc.dim)
    total_var = float(np.einsum("ij,ij->", sample, sample, dtype=np.float64))
    comp *= np.where(comp[np.abs(comp).argmax(0), np.arange(comp.shape[1])] < 0, -1.0, 1.0)
    var = np.maximum(w, 0) / max(n - 1, 1)
    scale = (
        1 / np.sqrt(var + WHITEN_EPS * max(float(var.max()), 1e-30))
        if pc.whiten
        else np.ones(pc.dim)
    )
    np.save(tmp / "mean.npy", mean.astype(np.float32))
    np.save(tmp / "components.npy", comp.astype(np.float32))
    np.save(tmp / "scale.npy", scale.astype(np.float32))
    return {
        "fitted_on": int(n),
        "input_dim": int(D),
        "dim": int(pc.dim),
        "explained_variance": round(float(np.maximum(w, 0).sum()) / total_var, 6)
        if total_var > 0
        else 1.0,
    }


def load_projection(model_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean (D,), components (D, dim), scale (dim,)) of a fitted projection entry."""
    mean, components, scale = (
        np.load(model_dir / f) for f in ("mean.npy", "components.npy", "scale.npy")
    )
    return mean, components, scale


def project(x: np.ndarray, mean: np.ndarray, comp: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Projected, L2-normalised float32 rows of ``x`` (n, D) -> (n, dim)."""
    return normalize(((np.asarray(x, np.float32) - mean) @ comp) * scale)

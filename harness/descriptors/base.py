"""Descriptor interface and the training-free descriptors."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from harness.descriptors.config import DescriptorConfig
from harness.errors import ConfigError
from harness.methods import Registry


def normalize(x: np.ndarray) -> np.ndarray:
    """Row-wise L2 normalisation (zero rows stay zero)."""
    x = np.asarray(x, np.float32)
    n = np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.where(n > 0, n, 1)


class Descriptor:
    """Maps uint8 crops ``(B, S, S, 3)`` (RGB, S = ``input_size``) to float32 ``(B, dim)``.

    ``needs_training`` descriptors get ``fit`` on reference subimages before use, and save and
    load their state under a directory.
    """

    name = "base"
    needs_training = False

    def __init__(self, cfg: DescriptorConfig) -> None:
        self.cfg = cfg

    @property
    def input_size(self) -> int:
        """Side of the square crops the descriptor reads, pixels."""
        return self.cfg.input_size

    def fit(
        self,
        crops: np.ndarray,
        out_dir: Path,
        progress: Callable[[int], object] | None = None,
    ) -> dict[str, Any]:  # pragma: no cover - trivial
        """Train on ``crops`` (N, S, S, 3) uint8 and write the model into ``out_dir``.

        Args:
            crops: Training crops (an array or a memmap).
            out_dir: The model entry's directory.
            progress: Called with the number of samples of each training step, when given.

        Returns:
            What the model entry's manifest records (losses, steps); empty for untrained ones.
        """
        return {}

    def load(self, out_dir: Path) -> None:  # pragma: no cover - trivial
        """Load what :meth:`fit` wrote into ``out_dir`` (nothing for untrained descriptors)."""
        return None

    def encode(self, crops: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 RGB crops -> (N, D) float32 descriptors."""
        raise NotImplementedError


def hog(gray: np.ndarray, cell: int = 8, bins: int = 9) -> np.ndarray:
    """Dalal-Triggs HOG of a grey image.

    Unsigned orientations with linear bin interpolation, 2x2-cell blocks with stride one cell,
    L2-Hys normalisation (clip 0.2).
    """
    g = gray.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=1)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=1)
    mag = np.sqrt(gx * gx + gy * gy)
    ang = (np.degrees(np.arctan2(gy, gx)) % 180.0) / (180.0 / bins)
    lo = np.floor(ang).astype(np.int64) % bins
    frac = ang - np.floor(ang)
    h, w = g.shape
    cy, cx = h // cell, w // cell
    hist = np.zeros((cy, cx, bins), np.float32)
    ci = (np.arange(cy * cell) // cell)[:, None].repeat(cx * cell, 1)
    cj = (np.arange(cx * cell) // cell)[None, :].repeat(cy * cell, 0)
    m, lb, f = (
        mag[: cy * cell, : cx * cell],
        lo[: cy * cell, : cx * cell],
        frac[: cy * cell, : cx * cell],
    )
    np.add.at(hist, (ci, cj, lb), m * (1 - f))
    np.add.at(hist, (ci, cj, (lb + 1) % bins), m * f)
    blocks = np.concatenate([hist[:-1, :-1], hist[1:, :-1], hist[:-1, 1:], hist[1:, 1:]], axis=2)
    blocks /= np.linalg.norm(blocks, axis=2, keepdims=True) + 1e-6
    blocks = np.minimum(blocks, 0.2)
    blocks /= np.linalg.norm(blocks, axis=2, keepdims=True) + 1e-6
    return blocks.ravel()


class HogDescriptor(Descriptor):
    """Histogram of oriented gradients of the grey crop resized to 64x64 (1,764 dims)."""

    name = "hog"

    def encode(self, crops: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 RGB crops -> (N, 1764) HOG descriptors."""
        out = []
        for c in crops:
            g = cv2.cvtColor(c, cv2.COLOR_RGB2GRAY)
            if g.shape != (64, 64):
                g = cv2.resize(g, (64, 64), interpolation=cv2.INTER_AREA)
            out.append(hog(g))
        return np.asarray(out, np.float32).reshape(len(crops), -1)


class ThumbDescriptor(Descriptor):
    """A 16x16 zero-mean grey thumbnail beside an 8x4x4 HSV colour histogram (equal weight)."""

    name = "thumb"

    def encode(self, crops: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 RGB crops -> (N, 384) thumbnail + colour histogram descriptors."""
        out = []
        for c in crops:
            g = (
                cv2.resize(
                    cv2.cvtColor(c, cv2.COLOR_RGB2GRAY), (16, 16), interpolation=cv2.INTER_AREA
                )
                .astype(np.float32)
                .ravel()
            )
            g -= g.mean()
            g /= np.linalg.norm(g) + 1e-6
            hsv = cv2.cvtColor(c, cv2.COLOR_RGB2HSV)
            hist = cv2.calcHist([hsv], [0, 1, 2], None, [8, 4, 4], [0, 180, 0, 256, 0, 256]).ravel()
            hist /= np.linalg.norm(hist) + 1e-6
            out.append(np.concatenate([g, hist]))
        return np.asarray(out, np.float32).reshape(len(crops), -1)


class SeqslamDescriptor(Descriptor):
    """SeqSLAM's patch-normalised thumbnail: no training, made for pairing frames across seasons.

    The grey crop shrunk to ``SIDE`` x ``SIDE`` pixels (area interpolation), each ``PATCH`` x
    ``PATCH`` patch standardised to zero mean and unit deviation (local contrast normalisation,
    as SeqSLAM, Milford and Wyeth 2012, prepares its images), flattened; the caller L2-normalises,
    so the squared distance the engine ranks by is SeqSLAM's difference of normalised patches.
    """

    name = "seqslam"
    #: The thumbnail's side and the patch a contrast is normalised over, pixels (SeqSLAM's
    #: proportions: 8-pixel patches on a thumbnail a few patches a side).
    SIDE, PATCH = 32, 8

    def encode(self, crops: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 RGB crops -> (N, SIDE * SIDE) patch-normalised thumbnails."""
        n, p = self.SIDE, self.PATCH
        out = np.empty((len(crops), n * n), np.float32)
        for i, c in enumerate(crops):
            g = cv2.resize(
                cv2.cvtColor(c, cv2.COLOR_RGB2GRAY), (n, n), interpolation=cv2.INTER_AREA
            )
            b = g.astype(np.float32).reshape(n // p, p, n // p, p).transpose(0, 2, 1, 3)
            b = (b - b.mean(axis=(2, 3), keepdims=True)) / (
                b.std(axis=(2, 3), keepdims=True) + 1e-6
            )
            out[i] = b.transpose(0, 2, 1, 3).reshape(-1)
        return out


#: Descriptors by ``[descriptor] name``; a user's is added with ``REGISTRY.add(name, cls)``.
REGISTRY: Registry[type[Descriptor]] = Registry("descriptor")
REGISTRY.add("hog", HogDescriptor)
REGISTRY.add("thumb", ThumbDescriptor)
REGISTRY.add("seqslam", SeqslamDescriptor)


def make_descriptor(cfg: DescriptorConfig) -> Descriptor:
    """The descriptor ``[descriptor] name`` selects from :data:`REGISTRY`.

    Raises:
        ConfigError: The name is not registered.
    """
    if cfg.name not in REGISTRY:
        raise ConfigError(f"[descriptor] unknown name {cfg.name!r}; known: {sorted(REGISTRY)}")
    return REGISTRY[cfg.name](cfg)

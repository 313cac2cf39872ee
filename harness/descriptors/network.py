"""A user's own network as the subimage descriptor: TorchScript (torch) or ONNX (``cv2.dnn``).

``[descriptor] name = "torchscript"`` or ``"onnx"`` with ``path`` (a local file: nothing is
downloaded), ``input_size`` (the square side the network reads), ``mean``/``std`` (per RGB channel,
applied to values scaled to [0, 1]) and ``pooling`` of a feature map: ``avg``, ``max`` or ``gem``
(generalised mean, exponent ``gem_p``, Radenović et al.). A network that already returns
``(N, D)`` vectors is used as it is. Descriptors are L2-normalised by the encoding stage like
every other descriptor's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from harness.descriptors.base import Descriptor
from harness.descriptors.config import DescriptorConfig
from harness.errors import ConfigError, HarnessError

POOLINGS = ("avg", "max", "gem")


def pool(y: np.ndarray, how: str, p: float = 3.0) -> np.ndarray:
    """``(N, C, H, W)`` feature maps -> ``(N, C)``; ``(N, D)`` passes; anything else flattens."""
    y = np.asarray(y, np.float32)
    if y.ndim != 4:
        return y.reshape(len(y), -1)
    if how == "max":
        return y.max(axis=(2, 3))
    if how == "gem":
        return np.power(np.power(np.clip(y, 1e-6, None), p).mean(axis=(2, 3)), 1.0 / p)
    return y.mean(axis=(2, 3))


class NetworkDescriptor(Descriptor):
    """The output of a user's network on each crop, pooled (see the module docstring)."""

    name = "network"

    def __init__(self, cfg: DescriptorConfig) -> None:
        super().__init__(cfg)
        self._net: Any = None

    def _input(self, crops: np.ndarray) -> np.ndarray:
        x = np.asarray(crops, np.float32) / np.float32(255.0)
        mean = np.asarray(self.cfg.mean, np.float32)
        std = np.asarray(self.cfg.std, np.float32)
        return np.ascontiguousarray(((x - mean) / std).transpose(0, 3, 1, 2), np.float32)

    def _forward(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def encode(self, crops: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 RGB crops -> (N, D) pooled network outputs.

        Raises:
            HarnessError: The network's output holds NaN or inf (named with the file).
        """
        if not len(crops):
            return np.zeros((0, 0), np.float32)
        y = pool(self._forward(self._input(crops)), self.cfg.pooling, self.cfg.gem_p)
        if not np.isfinite(y).all():
            raise HarnessError(
                f"{self.cfg.path}: the network's output holds NaN or inf for "
                f"{int((~np.isfinite(y).all(1)).sum())} of {len(y)} crops; check mean/std "
                "and the exported model"
            )
        return y


class TorchScriptDescriptor(NetworkDescriptor):
    """A TorchScript file (``torch.jit.save``), run on the CPU."""

    name = "torchscript"

    def _forward(self, x: np.ndarray) -> np.ndarray:
        import torch

        if self._net is None:
            try:
                self._net = torch.jit.load(str(Path(self.cfg.path)), map_location="cpu").eval()
            except (RuntimeError, ValueError) as err:
                raise ConfigError(f"{self.cfg.path}: not a TorchScript model ({err})") from None
        with torch.inference_mode():
            y = self._net(torch.from_numpy(x))
        if isinstance(y, (list, tuple)):
            y = y[0]
        return np.asarray(y.float().numpy())


class OnnxDescriptor(NetworkDescriptor):
    """An ONNX file, run by OpenCV's ``cv2.dnn`` (no other runtime)."""

    name = "onnx"

    def _forward(self, x: np.ndarray) -> np.ndarray:
        if self._net is None:
            try:
                self._net = cv2.dnn.readNetFromONNX(str(Path(self.cfg.path)))
            except cv2.error as err:
                raise ConfigError(
                    f"{self.cfg.path}: not an ONNX model OpenCV can read "
                    f"({str(err).strip()[-200:]})"
                ) from None
        out = []
        for row in x:  # one crop a call: an export may fix the batch size
            self._net.setInput(row[None])
            out.append(np.asarray(self._net.forward(), np.float32)[0])
        return np.stack(out)

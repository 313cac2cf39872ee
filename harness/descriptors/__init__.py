"""Subimage descriptors: a registry of encoders from uint8 crops to L2-normalised vectors.

``autoencoder`` (the paper's, trained without labels) is the default; ``hog`` and ``thumb``
need no training; ``torchscript`` and ``onnx`` run a user's own network from a local file.
A user's own descriptor is a small class: subclass :class:`Descriptor`,
implement ``encode`` (and ``fit`` if it learns), and add it to ``REGISTRY``.
"""

from __future__ import annotations

from harness.descriptors.autoencoder_descriptor import AutoencoderDescriptor
from harness.descriptors.base import (
    REGISTRY,
    Descriptor,
    HogDescriptor,
    ThumbDescriptor,
    make_descriptor,
    normalize,
)
from harness.descriptors.network import OnnxDescriptor, TorchScriptDescriptor

REGISTRY.add("autoencoder", AutoencoderDescriptor)
REGISTRY.add("torchscript", TorchScriptDescriptor)
REGISTRY.add("onnx", OnnxDescriptor)

__all__ = [
    "REGISTRY",
    "AutoencoderDescriptor",
    "Descriptor",
    "HogDescriptor",
    "OnnxDescriptor",
    "ThumbDescriptor",
    "TorchScriptDescriptor",
    "make_descriptor",
    "normalize",
]

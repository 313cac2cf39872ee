"""The autoencoder: shapes, training, determinism, checkpoints; the training-free descriptors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from harness.config import DescriptorConfig
from harness.descriptors import AutoencoderDescriptor, HogDescriptor, ThumbDescriptor, normalize
from harness.descriptors.autoencoder import ConvAutoencoder, load_checkpoint


def test_paper_architecture_gives_a_16384_dim_bottleneck() -> None:
    model = ConvAutoencoder().eval()
    x = torch.rand(2, 3, 256, 256)
    with torch.no_grad():
        assert model.encode(x).shape == (2, 16 * 32 * 32)
        assert model(x).shape == x.shape
    convs = [m for m in model.encoder.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 3 and all(c.kernel_size == (3, 3) for c in convs)
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in model.encoder.modules()) == 3
    assert sum(isinstance(m, torch.nn.MaxPool2d) for m in model.encoder.modules()) == 3


def _crops(n: int = 96, size: int = 32) -> np.ndarray:
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (8, size, size, 3), dtype=np.uint8)
    return base[rng.integers(0, 8, n)]


def test_training_lowers_the_loss_and_is_reproducible(tmp_path: Path) -> None:
    cfg = DescriptorConfig(input_size=32, epochs=3, batch_size=16, seed=7, device="cpu")
    a, b = AutoencoderDescriptor(cfg), AutoencoderDescriptor(cfg)
    info = a.fit(_crops(), tmp_path / "a")  # type: ignore[arg-type]
    b.fit(_crops(), tmp_path / "b")  # type: ignore[arg-type]
    assert info["last_epoch_loss"] < info["first_epoch_loss"]
    x = _crops(10)
    assert np.array_equal(a.encode(x), b.encode(x))
    assert (tmp_path / "a" / "loss.csv").read_text() == (tmp_path / "b" / "loss.csv").read_text()
    assert (tmp_path / "a" / "loss.png").exists()


def test_checkpoint_round_trip_with_weights_only(tmp_path: Path) -> None:
    cfg = DescriptorConfig(input_size=32, epochs=1, batch_size=16, device="cpu")
    a = AutoencoderDescriptor(cfg)
    a.fit(_crops(32), tmp_path)  # type: ignore[arg-type]
    b = AutoencoderDescriptor(cfg)
    b.load(tmp_path)
    x = _crops(5)
    assert np.array_equal(a.encode(x), b.encode(x))
    _model, meta = load_checkpoint(tmp_path / "autoencoder.pt", torch.device("cpu"))
    assert meta["channels"] == [32, 32, 16]


def test_training_free_descriptors() -> None:
    x = _crops(4, 64)
    h = HogDescriptor(DescriptorConfig()).encode(x)
    t = ThumbDescriptor(DescriptorConfig()).encode(x)
    assert h.shape == (4, 7 * 7 * 36) and t.shape == (4, 256 + 128)
    n = normalize(h)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, rtol=1e-5)
    assert np.array_equal(HogDescriptor(DescriptorConfig()).encode(x), h)

"""The autoencoder: shapes, training, determinism, checkpoints; the training-free descriptors."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from harness.descriptors import AutoencoderDescriptor, HogDescriptor, ThumbDescriptor, normalize
from harness.descriptors.autoencoder import (
    ConvAutoencoder,
    MaxPool2x2,
    held_out_loss,
    inference_encoder,
    load_checkpoint,
    reconstruct,
    to_tensor,
)
from harness.descriptors.config import DescriptorConfig
from harness.descriptors.extract import torch_threads
from harness.runtime.hardware import resolve_precision


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


def test_inference_encoder_equals_the_trained_encoder() -> None:
    """Folded batch-norm, pool-before-ReLU and micro-batches give the model's own encoding."""
    torch.manual_seed(3)
    model = ConvAutoencoder().eval()
    for bn in (
        m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)
    ):  # non-trivial statistics
        bn.running_mean.uniform_(-0.2, 0.2)
        bn.running_var.uniform_(0.5, 2.0)
        bn.weight.data.uniform_(0.5, 1.5)
        bn.bias.data.uniform_(-0.2, 0.2)
    x = to_tensor(_crops(6, 64), torch.device("cpu"), per_crop=True)
    with torch.no_grad():
        ref = model.encode(x.contiguous())
        fused = inference_encoder(model)(x)
    assert fused.shape == ref.shape == (6, 16 * 8 * 8)
    assert torch.allclose(fused, ref, atol=1e-5, rtol=1e-4)
    for step in (1, 2, 6):
        d = AutoencoderDescriptor(
            DescriptorConfig(
                input_size=64,
                input_norm="per_crop",
                device="cpu",
                encode_batch=step,
                precision="fp32",  # the model's own (fp32) arithmetic, on a bf16 CPU too
            )
        )
        d.model = model
        assert np.allclose(d.encode(_crops(6, 64)), ref.numpy(), atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize(
    "shape", [(2, 32, 256, 256), (3, 16, 64, 64), (2, 8, 7, 9), (1, 1, 8, 8), (4, 3, 6, 10)]
)
def test_the_2x2_pool_is_max_pool_bit_for_bit(shape: tuple[int, int, int, int]) -> None:
    """Channels-last, plain and odd-sized inputs, NaN included: the values of ``max_pool2d``."""
    y = torch.randn(shape, generator=torch.Generator().manual_seed(1))
    y.view(-1)[::97] = float("nan")
    for x in (y.contiguous(memory_format=torch.channels_last), y.contiguous()):
        got, ref = MaxPool2x2()(x), torch.nn.functional.max_pool2d(x, 2)
        assert got.shape == ref.shape
        assert torch.equal(got.isnan(), ref.isnan())
        assert torch.equal(got.nan_to_num(), ref.nan_to_num())


def test_held_out_reconstruction_one_at_a_time_is_the_batch_bit_for_bit() -> None:
    """At 256 x 256 the held-out loss goes one subimage at a time: the same bits as the batch."""
    torch.manual_seed(5)
    model = ConvAutoencoder().to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    data = _crops(12, 256)
    model.train()
    model(to_tensor(data[:8], torch.device("cpu"), True))  # batch-norm statistics to use
    model.eval()
    x = to_tensor(data[:5], torch.device("cpu"), True)
    with torch.no_grad(), torch_threads():
        assert torch.equal(reconstruct(model, x), model(x))
        batched = float(torch.nn.functional.mse_loss(model(x), x))
    hold = np.arange(5)
    with torch_threads():  # as in training: the held-out loss runs on its two threads
        assert held_out_loss(model, data, hold, 8, torch.device("cpu"), True) == batched
    assert model.training  # handed back in training mode, as the training loop expects


def test_bf16_trains_and_encodes_in_bfloat16_close_to_fp32(tmp_path: Path) -> None:
    """``precision = "bf16"``: autocast in training and encoding; the descriptors of the same
    weights stay within bf16's rounding of the fp32 ones, and the run is deterministic."""
    cfg = DescriptorConfig(input_size=32, epochs=2, batch_size=16, seed=7, device="cpu")
    fp = AutoencoderDescriptor(cfg)
    bf = AutoencoderDescriptor(dataclasses.replace(cfg, precision="bf16"))
    assert fp.bf16 == (resolve_precision("auto", "cpu") == "bf16")  # auto: native bf16 only
    assert bf.bf16
    info = bf.fit(_crops(), tmp_path / "bf")  # type: ignore[arg-type]
    assert info["last_epoch_loss"] < info["first_epoch_loss"]  # it learns in bf16
    again = AutoencoderDescriptor(dataclasses.replace(cfg, precision="bf16"))
    again.fit(_crops(), tmp_path / "again")  # type: ignore[arg-type]
    x = _crops(12)
    assert np.array_equal(bf.encode(x), again.encode(x))  # deterministic
    fp32 = AutoencoderDescriptor(dataclasses.replace(cfg, precision="fp32"))
    fp32.model = bf.model  # the same weights, encoded both ways
    a, b = normalize(fp32.encode(x)), normalize(bf.encode(x))
    assert not np.array_equal(a, b)  # bf16 arithmetic was used
    cos = (a * b).sum(1)
    assert cos.min() > 0.995, cos  # each descriptor within bf16 rounding of its fp32 one


def test_per_crop_normalisation_matches_its_definition() -> None:
    """sigmoid((x - mean) / std) per crop and channel, std unbiased, on [0, 1] values."""
    c = _crops(3, 16)
    x = torch.from_numpy(c).permute(0, 3, 1, 2).double() / 255
    mu, sd = x.mean(dim=(2, 3), keepdim=True), x.std(dim=(2, 3), keepdim=True).clamp_min(1e-3)
    want = torch.sigmoid((x - mu) / sd)
    got = to_tensor(c, torch.device("cpu"), per_crop=True)
    assert got.stride()[1] == 1  # channels-last memory
    assert torch.allclose(got.double(), want, atol=1e-6)
    flat = np.full((1, 8, 8, 3), 77, np.uint8)  # a flat crop: std clamps, no division by zero
    assert torch.allclose(
        to_tensor(flat, torch.device("cpu"), per_crop=True), torch.full((1, 3, 8, 8), 0.5)
    )


def test_per_crop_lookup_gives_the_whole_tensors_bits() -> None:
    """On the CPU ``to_tensor`` maps the 256 uint8 values and looks the pixels up: the same bits
    as the affine map and logistic applied to the whole uint8 tensor, at 1 and 2 threads, for
    crops of any size, range and batch (a flat channel included)."""
    rng = np.random.default_rng(3)
    threads = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            for size, batch, lo, hi in ((256, 2, 0, 255), (64, 5, 40, 90), (96, 16, 0, 255),
                                        (32, 3, 200, 200)):  # fmt: skip
                c = rng.integers(lo, hi + 1, (batch, size, size, 3), dtype=np.uint8)
                c[0, ..., 1] = 17
                st = np.array([cv2.meanStdDev(x) for x in c]).reshape(batch, 2, 3)
                sd = np.maximum(st[:, 1] / 255 * np.sqrt(size**2 / (size**2 - 1)), 1e-3)
                a = torch.from_numpy((1 / (255 * sd)).astype(np.float32))[:, :, None, None]
                b = torch.from_numpy((-st[:, 0] / 255 / sd).astype(np.float32))[:, :, None, None]
                whole = torch.addcmul(b, torch.from_numpy(c).permute(0, 3, 1, 2), a).sigmoid_()
                got = to_tensor(c, torch.device("cpu"), per_crop=True)
                assert got.is_contiguous(memory_format=torch.channels_last)
                assert torch.equal(got, whole), (n, size, batch)
    finally:
        torch.set_num_threads(threads)


def test_training_free_descriptors() -> None:
    x = _crops(4, 64)
    h = HogDescriptor(DescriptorConfig()).encode(x)
    t = ThumbDescriptor(DescriptorConfig()).encode(x)
    assert h.shape == (4, 7 * 7 * 36) and t.shape == (4, 256 + 128)
    n = normalize(h)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, rtol=1e-5)
    assert np.array_equal(HogDescriptor(DescriptorConfig()).encode(x), h)


def test_hog_values_on_hand_built_edges() -> None:
    """A vertical step edge has horizontal gradients only (orientation 0: bin 0); a horizontal one
    has orientation 90 degrees, which lies half-way between bins 4 and 5 (20-degree bins)."""
    from harness.descriptors.base import hog

    img = np.zeros((64, 64), np.uint8)
    img[:, 32:] = 255
    v = hog(img).reshape(7, 7, 4, 9)
    assert v.max() > 0
    assert np.abs(v[..., 1:]).max() == 0  # all energy in bin 0
    assert (
        np.abs(v[:, [0, 1, 5, 6]]).max() == 0
    )  # blocks away from the edge (columns 31-32) are empty
    h = hog(img.T.copy()).reshape(7, 7, 4, 9)
    nz = h[h.sum(-1) > 0]
    np.testing.assert_allclose(nz[:, 4], nz[:, 5], rtol=1e-5)
    assert np.abs(np.delete(nz, [4, 5], axis=-1)).max() == 0


def test_thumbnail_values_on_a_flat_grey_crop() -> None:
    """Flat grey: the zero-mean thumbnail is all zeros; the HSV histogram is one-hot at
    (H bin 0, S bin 0, V bin 128 // 64 = 2), flat index 2, with unit norm."""
    crop = np.full((1, 64, 64, 3), 128, np.uint8)
    t = ThumbDescriptor(DescriptorConfig()).encode(crop)[0]
    assert np.abs(t[:256]).max() == 0
    hist = t[256:]
    assert hist[2] == pytest.approx(1.0, abs=1e-5) and np.abs(np.delete(hist, 2)).max() == 0


def test_training_on_a_sample_budget_with_early_stopping(tmp_path: Path) -> None:
    """A budget in samples bounds the steps whatever the crop count; held-out crops stop it early
    once their loss stops improving, and the best weights are kept. Seeded: the same twice."""
    from harness.descriptors.autoencoder import EarlyStop, TrainSettings, train_budget

    x = _crops(64, 32)
    runs = []
    for _ in range(2):
        torch.manual_seed(0)
        model = ConvAutoencoder((8, 8, 4))
        hist, info = train_budget(
            model,
            x,
            samples=40 * 8,
            settings=TrainSettings(batch_size=8, lr=3e-3, seed=0, device=torch.device("cpu")),
            stop=EarlyStop(holdout=0.25, eval_every=5, patience=100),
        )
        runs.append((hist, info))
    hist, info = runs[0]
    assert (
        info["steps"] == 40
        and len(hist) == 40
        and info["held_out"] == 16
        and not info["stopped_early"]
    )
    assert runs[0][1]["held_out_curve"] == runs[1][1]["held_out_curve"]  # reproducible
    curve = [v for _, v in info["held_out_curve"]]
    assert curve[-1] < curve[0]  # the held-out loss falls
    assert info["best_held_out_loss"] == min(curve)
    # patience 1 with a learning rate that diverges: it stops at the first evaluation without
    # improvement
    model = ConvAutoencoder((8, 8, 4))
    _, info = train_budget(
        model,
        x,
        samples=200 * 8,
        settings=TrainSettings(batch_size=8, lr=5.0, seed=0, device=torch.device("cpu")),
        stop=EarlyStop(holdout=0.25, eval_every=2, patience=1),
    )
    assert info["stopped_early"] and info["steps"] < 200


def test_lanes_encode_the_descriptors_of_one_batch_at_a_time(tmp_path: Path, monkeypatch) -> None:
    """Two lanes (each frame batch decoded, cropped and encoded in its own thread, torch at one
    thread, the batches handed on in groups) give the bytes of one batch at a time with all of
    torch's threads, in order."""
    import cv2
    import pandas as pd

    from harness.descriptors import extract

    rng = np.random.default_rng(3)
    frames, rows = [], []
    for t in range(20):  # 20 frames: three batches of 8, two lanes, more batches than lanes ahead
        path = tmp_path / f"f{t}.jpg"
        cv2.imwrite(str(path), rng.integers(0, 256, (96, 128, 3), dtype=np.uint8))
        frames.append({"session": "s", "camera": "c", "utime": t, "image": str(path)})
        for k in range(3):
            x, y = int(rng.integers(0, 60)), int(rng.integers(0, 40))
            rows.append({"session": "s", "camera": "c", "utime": t, "proposal_method": "m",
                         "box_id": k, "x1": x, "y1": y, "x2": x + 60, "y2": y + 50})  # fmt: skip
    fr, props = pd.DataFrame(frames), pd.DataFrame(rows).sample(frac=1.0, random_state=0)
    dc = DescriptorConfig(input_size=32, device="cpu")
    desc = AutoencoderDescriptor(dc)
    torch.manual_seed(0)
    desc.model = ConvAutoencoder().eval()

    def encoded() -> np.ndarray:
        out = np.full((len(props), 16 * 4 * 4), np.nan, np.float32)
        for pos, v in extract._encoded(desc, dc, fr, props, "test"):
            out[pos] = v
        return out

    monkeypatch.setattr(extract, "LANE_GROUP_ROWS", 50)  # groups of two batches of 8 frames
    with torch_threads(2):
        assert extract._lanes(desc, dc) == 2
        assert extract._lanes(desc, dataclasses.replace(dc, num_workers=1)) == 1
        in_lanes = encoded()
        monkeypatch.setattr(extract, "_lanes", lambda d, c: 1)
        one_at_a_time = encoded()
    assert np.isfinite(in_lanes).all()
    assert in_lanes.tobytes() == one_at_a_time.tobytes()

"""The paper's convolutional autoencoder (method §6).

Encoder: three blocks of conv 3x3 + batch-norm + ReLU + max-pool 2x2; a 256x256 RGB input gives a
16 x 32 x 32 = 16,384-dim bottleneck, the descriptor. The decoder mirrors the encoder. Trained
without labels (reconstruction loss) on reference-session subimages.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import cv2
import numpy as np
import torch
from torch import nn

from harness.errors import HarnessError
from harness.runtime.cache import atomic_path

log = logging.getLogger(__name__)


def _enc_block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(2),
    )


def _dec_block(cin: int, cout: int, last: bool) -> nn.Sequential:
    layers: list[nn.Module] = [
        nn.Upsample(scale_factor=2, mode="nearest"),
        nn.Conv2d(cin, cout, 3, padding=1, bias=last),
    ]
    layers += [nn.Sigmoid()] if last else [nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class ConvAutoencoder(nn.Module):
    """Three conv blocks down, three mirrored blocks up. ``channels`` are the encoder's widths."""

    def __init__(self, channels: Sequence[int] = (32, 32, 16)) -> None:
        super().__init__()
        c1, c2, c3 = channels
        self.encoder = nn.Sequential(_enc_block(3, c1), _enc_block(c1, c2), _enc_block(c2, c3))
        self.decoder = nn.Sequential(
            _dec_block(c3, c2, False), _dec_block(c2, c1, False), _dec_block(c1, 3, True)
        )

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, S, S) float images -> (B, D) flattened bottleneck activations."""
        return self.encoder(x).flatten(1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, S, S) -> its reconstruction, the same shape."""
        return self.decoder(self.encoder(x))


def to_tensor(crops: np.ndarray, device: torch.device, per_crop: bool = False) -> torch.Tensor:
    """uint8 (B, S, S, 3) -> float (B, 3, S, S) in [0, 1], in channels-last memory.

    NHWC strides: the layout oneDNN's convolutions run fastest in.

    With ``per_crop`` each crop's channels are standardised (zero mean, unit variance), then
    squashed back into (0, 1) by a logistic, which removes global illumination and colour cast.
    The statistics come from OpenCV on the uint8 crop. A uint8 value has 256 possible values, so
    on the CPU the affine map plus logistic is computed once for each of them, by the same torch
    calls on the same dtypes, and OpenCV's ``LUT`` looks every pixel up: the same bits as mapping
    the whole tensor, in 0.2 ms a 256 x 256 crop against 0.9 ms (one thread, measured).
    """
    crops = np.ascontiguousarray(crops)
    x = torch.from_numpy(crops).to(device).permute(0, 3, 1, 2)
    if not per_crop:
        return x.float().div_(255.0)
    n = crops.shape[1] * crops.shape[2]
    st = np.array([cv2.meanStdDev(c) for c in crops], np.float64).reshape(len(crops), 2, -1)
    mu = st[:, 0] / 255.0
    sd = np.maximum(st[:, 1] / 255.0 * np.sqrt(n / max(n - 1, 1)), 1e-3)  # unbiased, like torch.std
    a = torch.from_numpy((1.0 / (255.0 * sd)).astype(np.float32)).to(device)[:, :, None, None]
    b = torch.from_numpy((-mu / sd).astype(np.float32)).to(device)[:, :, None, None]
    if device.type != "cpu" or crops.ndim != 4 or crops.shape[-1] not in (1, 3, 4):
        return torch.addcmul(b, x, a).sigmoid_()
    values = torch.arange(256, dtype=torch.uint8).expand(len(crops), crops.shape[-1], 1, 256)
    table = torch.addcmul(b, values, a).sigmoid_()[:, :, 0].permute(0, 2, 1).contiguous().numpy()
    out = np.empty(crops.shape, np.float32)
    for crop, lut, dst in zip(crops, table, out, strict=True):
        cv2.LUT(crop, lut[None], dst=dst)
    return torch.from_numpy(out).permute(0, 3, 1, 2)


def autocast(device: torch.device, bf16: bool) -> torch.autocast:
    """``torch.autocast`` in bfloat16 on ``device`` when ``bf16``, else a no-op context."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)


class MaxPool2x2(nn.Module):
    """The maximum of each 2 x 2 block: ``nn.MaxPool2d(2)``'s values, bit for bit.

    On a channels-last batch of even height and width it takes two elementwise maxima over views
    of the same memory (row pairs, then column pairs); torch's channels-last pooling of the first
    block's 32 x 256 x 256 activations takes about 3x as long (1.8 ms against 0.6 ms for two
    subimages, measured). Any other input goes to ``max_pool2d``. Maxima are exact, so the values
    are the pool's.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, H // 2, W // 2), each value the maximum of its 2 x 2 block."""
        b, c, h, w = x.shape
        if h % 2 or w % 2 or c < 2 or not x.is_contiguous(memory_format=torch.channels_last):
            return nn.functional.max_pool2d(x, 2)
        v = x.permute(0, 2, 3, 1).reshape(b, h // 2, 2, w // 2, 2 * c)
        rows = torch.maximum(v[:, :, 0], v[:, :, 1])  # (b, h/2, w/2, 2c): column pairs side by side
        return torch.maximum(rows[..., :c], rows[..., c:]).permute(0, 3, 1, 2)


def inference_encoder(model: ConvAutoencoder) -> nn.Sequential:
    """The trained encoder for inference, batch-norm folded into the convolutions.

    Each batch-norm is folded into its convolution's weights and bias, and max-pool moved before
    ReLU (they commute; ReLU then touches a quarter of the values) and taken by
    :class:`MaxPool2x2`. Same function as ``model.encode`` up to float rounding (checked in tests).
    """
    layers: list[nn.Module] = []
    for blk in model.encoder:
        conv, bn = cast(nn.Conv2d, blk[0]), cast(nn.BatchNorm2d, blk[1])  # type: ignore[index]
        mean, var = bn.running_mean, bn.running_var
        if mean is None or var is None:
            raise ValueError("inference_encoder needs batch-norm running statistics")
        scale = bn.weight.detach() / torch.sqrt(var + bn.eps)
        kernel, padding = (
            cast(tuple[int, int], conv.kernel_size),
            cast(tuple[int, int], conv.padding),
        )
        fused = nn.Conv2d(conv.in_channels, conv.out_channels, kernel, padding=padding, bias=True)
        fused.weight.data = conv.weight.detach() * scale[:, None, None, None]
        bias = conv.bias.detach() if conv.bias is not None else torch.zeros_like(scale)
        fused.bias = nn.Parameter((bias - mean) * scale + bn.bias.detach())
        layers += [fused, MaxPool2x2(), nn.ReLU(inplace=True)]
    layers.append(nn.Flatten(1))
    return nn.Sequential(*layers).to(next(model.parameters()).device).eval()


@dataclass(frozen=True)
class TrainSettings:
    """How the autoencoder trains, whatever its length (``[descriptor]``).

    ``progress`` is called with each step's sample count; ``per_crop`` normalises each crop by
    its own mean and spread; ``bf16`` runs the forward pass under ``torch.autocast`` in bfloat16
    (weights and optimizer stay float32).
    """

    batch_size: int
    lr: float
    seed: int
    device: torch.device
    progress: Callable | None = None
    per_crop: bool = False
    bf16: bool = False


@dataclass(frozen=True)
class EarlyStop:
    """A training budget's early stopping (``[descriptor]`` holdout, eval_every, patience).

    A seeded ``holdout`` share of the crops is never trained on and is measured every
    ``eval_every`` steps; ``patience`` evaluations without improvement stop it.
    """

    holdout: float = 0.1
    eval_every: int = 50
    patience: int = 4


def train(
    model: ConvAutoencoder, data: np.ndarray, epochs: int, settings: TrainSettings
) -> list[tuple[int, int, float]]:
    """Train on uint8 crops (N, S, S, 3) (an array or a memmap) with MSE for ``epochs`` passes.

    Returns (epoch, step, loss) rows.
    """
    batch_size, lr, seed, device = settings.batch_size, settings.lr, settings.seed, settings.device
    progress, per_crop, bf16 = settings.progress, settings.per_crop, settings.bf16
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    # channels-last: 2x faster steps on CPU than NCHW (not in torch's stubs for Module.to)
    model.to(device, memory_format=torch.channels_last)  # type: ignore[call-overload]
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    n = len(data)
    steps = math.ceil(n / batch_size)
    history = []
    it = range(epochs)
    for ep in it:
        perm = torch.randperm(n, generator=g).numpy()
        total = 0.0
        for s in range(steps):
            idx = np.sort(perm[s * batch_size : (s + 1) * batch_size])
            x = to_tensor(data[idx], device, per_crop)
            with autocast(device, bf16):
                loss = nn.functional.mse_loss(model(x).float(), x)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            lv = float(loss.detach())
            _finite_loss(lv, ep * steps + s)
            total += lv * len(idx)
            history.append((ep, ep * steps + s, lv))
            if progress:
                progress(1)
        log.info("autoencoder epoch %d/%d: mean loss %.5f", ep + 1, epochs, total / max(n, 1))
    model.eval()
    return history


def _finite_loss(value: float, step: int) -> None:
    """Stop at the first training step whose loss is NaN or inf (a diverged model ranks nothing).

    Raises:
        HarnessError: Naming the stage, the step and the value, and what to change.
    """
    if not math.isfinite(value):
        raise HarnessError(
            f"model: the autoencoder's training loss is {value} at step {step + 1}: training "
            "diverged; lower [descriptor] lr, or check the input crops"
        )


def split_holdout(n: int, holdout: float, g: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A seeded ``holdout`` share of ``n`` crops (sorted) and the rest (the training crops)."""
    perm = torch.randperm(n, generator=g).numpy()
    n_hold = min(max(1, round(n * holdout)), max(n - 1, 0)) if holdout > 0 and n > 1 else 0
    return np.sort(perm[:n_hold]), perm[n_hold:]


def held_out_loss(
    model: ConvAutoencoder,
    data: np.ndarray,
    hold: np.ndarray,
    batch_size: int,
    device: torch.device,
    per_crop: bool,
    bf16: bool = False,
) -> float:
    """Mean reconstruction loss over the held-out crops ``hold`` (the model left training)."""
    model.eval()
    with torch.no_grad(), autocast(device, bf16):
        tot = 0.0
        for s in range(0, len(hold), batch_size):
            x = to_tensor(data[hold[s : s + batch_size]], device, per_crop)
            tot += float(nn.functional.mse_loss(reconstruct(model, x).float(), x)) * len(x)
    model.train()
    return tot / max(len(hold), 1)


def reconstruct(model: ConvAutoencoder, x: torch.Tensor) -> torch.Tensor:
    """``model(x)`` of a model in eval mode, one subimage at a time on the CPU from 128 x 128 up.

    In eval mode each subimage's output depends on it alone. One at a time, a 256 x 256
    subimage's 8 MB of first-block activations stay in cache, which makes the held-out evaluation
    about 2x faster than batches of 16 (32 ms against 14 ms a subimage, measured). oneDNN gives
    the same bits at 128, 192 and 256 whatever the batch (checked at 256 in tests), but not at
    96 x 96 (measured), so smaller subimages, which gain little, go in whole batches, as a GPU's
    do.
    """
    big = x.dim() == 4 and x.shape[-1] * x.shape[-2] >= 128 * 128
    if x.device.type != "cpu" or model.training or len(x) < 2 or not big:
        return model(x)
    first = model(x[:1])
    out = torch.empty((len(x), *first.shape[1:]), dtype=first.dtype, device=first.device)
    out = out.contiguous(memory_format=torch.channels_last) if first.dim() == 4 else out
    out[:1] = first
    for i in range(1, len(x)):
        out[i : i + 1] = model(x[i : i + 1])
    return out


def train_budget(
    model: ConvAutoencoder,
    data: np.ndarray,
    samples: int,
    settings: TrainSettings,
    stop: EarlyStop = EarlyStop(),
) -> tuple[list[tuple[int, int, float]], dict]:
    """Train on a budget of ``samples`` sample-steps (not epochs), with early stopping.

    A seeded ``holdout`` share of the crops is never trained on; every ``eval_every`` steps its mean
    loss is measured, the best weights so far are kept, and training stops after ``patience``
    evaluations without improvement. The cost is bounded by ``samples`` whatever the session's
    length. Returns (epoch, step, loss) rows (epoch = passes over the training crops so far) and a
    summary: steps run, held-out loss curve, best step, whether it stopped early.
    """
    batch_size, lr, seed, device = settings.batch_size, settings.lr, settings.seed, settings.device
    progress, per_crop, bf16 = settings.progress, settings.per_crop, settings.bf16
    holdout, eval_every, patience = stop.holdout, stop.eval_every, stop.patience
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    hold, train_idx = split_holdout(len(data), holdout, g)
    n_hold = len(hold)
    model.to(device, memory_format=torch.channels_last)  # type: ignore[call-overload]
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    steps = max(1, math.ceil(samples / batch_size))
    history: list[tuple[int, int, float]] = []
    curve: list[tuple[int, float]] = []
    best, best_step, best_state, bad = float("inf"), 0, None, 0
    order, pos, epoch = np.array([], np.int64), 0, -1
    stopped = False

    for step in range(steps):
        if pos >= len(order):
            epoch += 1
            order = train_idx[torch.randperm(len(train_idx), generator=g).numpy()]
            pos = 0
        idx = np.sort(order[pos : pos + batch_size])
        pos += batch_size
        x = to_tensor(data[idx], device, per_crop)
        with autocast(device, bf16):
            loss = nn.functional.mse_loss(model(x).float(), x)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        history.append((epoch, step, float(loss.detach())))
        _finite_loss(history[-1][2], step)
        if progress:
            progress(1)
        if n_hold and ((step + 1) % eval_every == 0 or step + 1 == steps):
            hl = held_out_loss(model, data, hold, batch_size, device, per_crop, bf16)
            curve.append((step + 1, hl))
            if hl < best - 1e-7:
                best, best_step, bad = hl, step + 1, 0
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            else:
                bad += 1
                if bad >= patience:
                    stopped = True
                    break
    if best_state is not None:
        model.load_state_dict(best_state)
    model.eval()
    return history, {
        "steps": len(history),
        "held_out": n_hold,
        "held_out_curve": curve,
        "best_step": best_step,
        "best_held_out_loss": best if curve else float("nan"),
        "stopped_early": stopped,
    }


def save_checkpoint(path: Path, model: ConvAutoencoder, meta: dict) -> None:
    """Save atomically: state dict plus plain metadata (loadable with ``weights_only=True``)."""
    with atomic_path(Path(path)) as tmp:
        torch.save({"state_dict": model.state_dict(), "meta": meta}, tmp)


def load_checkpoint(path: Path, device: torch.device) -> tuple[ConvAutoencoder, dict]:
    """A saved autoencoder on ``device`` in eval mode, and its metadata."""
    ck = torch.load(Path(path), map_location=device, weights_only=True)
    meta = ck["meta"]
    model = ConvAutoencoder(tuple(meta["channels"]))
    model.load_state_dict(ck["state_dict"])
    return model.to(device).eval(), meta


def save_loss_curve(
    history: list[tuple[int, int, float]], csv_path: Path, png_path: Path | None
) -> None:
    """Write the training loss rows (epoch, step, loss) as CSV, and as a PNG plot when asked."""
    with atomic_path(csv_path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["epoch", "step", "loss"])
        w.writerows([(e, s, f"{v:.6f}") for e, s, v in history])
    if png_path is not None and history:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3))
        ax.plot([s for _, s, _ in history], [v for _, _, v in history], lw=1)
        ax.set_xlabel("step")
        ax.set_ylabel("reconstruction MSE")
        ax.set_yscale("log")
        ax.set_title("autoencoder training loss")
        fig.tight_layout()
        with atomic_path(png_path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
        plt.close(fig)

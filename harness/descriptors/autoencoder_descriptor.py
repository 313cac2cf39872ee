"""The autoencoder as a registered descriptor (training, checkpointing, encoding)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from harness.descriptors.autoencoder import (
    ConvAutoencoder,
    EarlyStop,
    TrainSettings,
    autocast,
    inference_encoder,
    load_checkpoint,
    save_checkpoint,
    save_loss_curve,
    to_tensor,
    train,
    train_budget,
)
from harness.descriptors.base import Descriptor
from harness.descriptors.config import DescriptorConfig
from harness.runtime.hardware import resolve_precision


def pick_device(name: str) -> torch.device:
    """``auto`` (CUDA where present), ``cpu`` or ``cuda`` as a torch device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class AutoencoderDescriptor(Descriptor):
    """The paper's descriptor: bottleneck activations of a convolutional autoencoder.

    Trained on the run's own subimages (``[descriptor]``); L2-normalised by the caller.
    """

    name = "autoencoder"
    needs_training = True
    CHECKPOINT = "autoencoder.pt"

    def __init__(self, cfg: DescriptorConfig) -> None:
        super().__init__(cfg)
        self.device = pick_device(cfg.device)
        # [descriptor] precision: bf16 arithmetic (autocast) where asked, or native under auto
        self.bf16 = resolve_precision(cfg.precision, self.device.type) == "bf16"
        self.model: ConvAutoencoder | None = None
        self._encoder: torch.nn.Module | None = None
        self._encoder_of: ConvAutoencoder | None = None

    @property
    def encode_batch(self) -> int:
        """Subimages per encoder call.

        On CPU two: the first block's activations (8 MB per 256x256 subimage) then stay in cache,
        which makes encoding about 4x faster than a batch of 32.
        """
        if self.cfg.encode_batch > 0:
            return self.cfg.encode_batch
        return self.cfg.batch_size if self.device.type == "cuda" else 2

    def fit(
        self,
        crops: np.ndarray,
        out_dir: Path,
        progress: Callable[[int], object] | None = None,
    ) -> dict[str, Any]:
        """Train on ``crops`` (N, S, S, 3) uint8 and save the checkpoint and loss curve.

        Args:
            crops: Training crops (an array or a memmap).
            out_dir: The model entry's directory.
            progress: Called with the number of samples of each training step, when given.

        Returns:
            The training summary for the entry's manifest.
        """
        torch.manual_seed(self.cfg.seed)
        model = ConvAutoencoder(tuple(self.cfg.channels))
        per_crop = self.cfg.input_norm == "per_crop"
        extra: dict = {}
        c = self.cfg
        settings = TrainSettings(
            c.batch_size, c.lr, c.seed, self.device, progress, per_crop, self.bf16
        )
        if c.train_samples > 0:  # a budget in samples with early stopping on held-out crops
            stop = EarlyStop(c.holdout, c.eval_every, c.patience)
            history, extra = train_budget(model, crops, c.train_samples, settings, stop)
        else:
            history = train(model, crops, c.epochs, settings)
        save_checkpoint(
            out_dir / self.CHECKPOINT,
            model,
            {"channels": list(self.cfg.channels), "input_size": self.cfg.input_size},
        )
        save_loss_curve(history, out_dir / "loss.csv", out_dir / "loss.png")
        self.model = model
        last_epoch = max((e for e, _, _ in history), default=0)
        first = float(np.mean([v for e, _, v in history if e == 0])) if history else float("nan")
        last = (
            float(np.mean([v for e, _, v in history if e == last_epoch]))
            if history
            else float("nan")
        )
        return {
            "train_subimages": len(crops),
            "first_epoch_loss": first,
            "last_epoch_loss": last,
            **extra,
        }

    def load(self, out_dir: Path) -> None:
        """Load the checkpoint of a model entry."""
        self.model, _ = load_checkpoint(out_dir / self.CHECKPOINT, self.device)

    @torch.inference_mode()
    def encode(self, crops: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 crops -> (N, D) float32 descriptors, in batches."""
        if self.model is None:
            raise RuntimeError("autoencoder is not trained or loaded")
        if self._encoder is None or self._encoder_of is not self.model:
            self._encoder, self._encoder_of = inference_encoder(self.model), self.model
        encoder = self._encoder
        step, per_crop = self.encode_batch, self.cfg.input_norm == "per_crop"
        with autocast(self.device, self.bf16):
            out = [
                encoder(to_tensor(crops[i : i + step], self.device, per_crop)).float().cpu().numpy()
                for i in range(0, len(crops), step)
            ]
        return np.concatenate(out) if out else np.zeros((0, 0), np.float32)

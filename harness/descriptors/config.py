"""The descriptor's config: ``[descriptor]`` and ``[projection]``, and their checks."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from harness.checks import check_value

#: ``[descriptor] precision``: the encoder's arithmetic (``auto``: fp32 on every device).
PRECISIONS = ("auto", "fp32", "bf16")


@dataclass(frozen=True)
class DescriptorConfig:
    """``[descriptor]``: the subimage descriptor, its training and encoding (method §6)."""

    # autoencoder (the paper's), hog, thumb, seqslam (no training), torchscript or onnx (a user's
    # network from path)
    name: str = "autoencoder"
    # the side, pixels, every subimage is resized to
    input_size: int = 256
    # the autoencoder's channels, layer by layer
    channels: tuple[int, int, int] = (32, 32, 16)
    input_norm: str = "none"  # "none" (the paper) or "per_crop": standardise each crop's channels
    # training epochs over the map's subimages (train_samples = 0)
    epochs: int = 4
    batch_size: int = 32  # training batch
    # subimages per encoder call; 0: 2 on CPU (keeps activations in cache), batch_size on GPU
    encode_batch: int = 0
    # the optimiser's learning rate
    lr: float = 1e-3
    # subimages of the map sessions the model is trained on, at most
    max_train_subimages: int = 4000
    # > 0: train on this many sample-steps (not epochs) with early stopping on held-out crops
    train_samples: int = 0
    # share of the training crops held out for early stopping (train_samples > 0)
    holdout: float = 0.1
    eval_every: int = 50  # steps between held-out evaluations
    patience: int = 4  # evaluations without improvement before training stops
    # how descriptors are stored: float16 or float32
    dtype: str = "float16"
    # auto (a CUDA GPU where there is one), cpu or cuda
    device: str = "auto"
    # the encoder's arithmetic, training and inference: "fp32", "bf16" (torch.autocast) or "auto"
    # (fp32 on every device, so a table does not depend on whether the machine multiplies bf16
    # natively; bf16 only where asked for by name)
    precision: str = "auto"
    # the training's and the crops' draws
    seed: int = 0
    # data-loader processes that decode crops (0: in the main process)
    num_workers: int = 0
    # frames per cached descriptor shard (the unit an interrupted run resumes at)
    shard_frames: int = 256
    # name = "torchscript" or "onnx": a user's network from a local file (its content is keyed)
    path: str = ""
    mean: tuple[float, float, float] = (0.485, 0.456, 0.406)  # per RGB channel, values in [0, 1]
    # per RGB channel, values in [0, 1]
    std: tuple[float, float, float] = (0.229, 0.224, 0.225)
    pooling: str = "avg"  # of a (N, C, H, W) output: "avg", "max" or "gem"
    # gem pooling's exponent
    gem_p: float = 3.0
    # "reduced": decode each frame at 1/2, 1/4 or 1/8 where every box keeps input_size pixels
    # (JPEG: libjpeg's scaled decode); "full": always the whole frame
    decode: str = "reduced"
    # batches of crops a reader thread decodes ahead of the encoder (0: none; with num_workers
    # > 0 the loader's processes decode ahead instead). 0 by default: on CPU the encoder already
    # uses every core, and the thread measured no faster (bench case crops); 2 with a GPU encoder
    prefetch: int = 0
    # threads that decode and crop the frames of a batch side by side, while the encoder waits
    # (OpenCV and libjpeg release the GIL); 0: as many as torch's intra-op threads, 1: none.
    # The crops are the same bytes whatever the number; ignored with num_workers > 0, and by the
    # autoencoder on CPU, which encodes in lanes (each batch decoded, cropped and encoded by one
    # of torch's threads: the same descriptors) with prefetch ignored as well
    crop_threads: int = 0
    # a folder of models trained before, each under the digest of what trains it (options, crops,
    # training code, torch, kernels): a run whose digest is there copies that model instead of
    # training (harness.descriptors.store; "": always train). No key holds it: the model is the
    # same either way
    trained_models: str = ""


@dataclass(frozen=True)
class ProjectionConfig:
    """Compact descriptors (docs/method.md).

    PCA or PCA-whitening to ``dim``, fitted on the reference sessions.
    """

    # 0: off, rank with the full descriptor (method §6); > 0: project to this many dimensions
    dim: int = 0
    whiten: bool = False  # divide each component by its standard deviation before re-normalising
    # reference subimages (a seeded sample) encoded to fit the directions; memory fit_samples x D x
    # 4 bytes
    fit_samples: int = 8192
    # the fit's draw of reference subimages
    seed: int = 0


def check_descriptor(de: DescriptorConfig, where: str) -> None:
    """``[descriptor]``: sizes, options, a user's network file."""
    c = check_value
    choices = (
        ("input_norm", ("none", "per_crop"), "'none' or 'per_crop'"),
        ("dtype", ("float16", "float32"), "float16 or float32"),
        ("precision", PRECISIONS, "'auto', 'fp32' or 'bf16'"),
        ("pooling", ("avg", "max", "gem"), "avg, max, gem"),
        ("decode", ("reduced", "full"), "reduced or full"),
    )
    for key, allowed, words in choices:
        c(getattr(de, key) in allowed, where, f"[descriptor] {key}", getattr(de, key), words)
    c(
        de.device in ("auto", "cpu", "cuda") or de.device.startswith("cuda:"),
        where,
        "[descriptor] device",
        de.device,
        "auto, cpu, cuda or cuda:N",
    )
    c(
        de.train_samples >= 0,
        where,
        "[descriptor] train_samples",
        de.train_samples,
        ">= 0 (0: train for epochs)",
    )
    c(0 <= de.holdout < 1, where, "[descriptor] holdout", de.holdout, "[0, 1)")
    c(
        de.eval_every >= 1 and de.patience >= 1,
        where,
        "[descriptor] eval_every, patience",
        (de.eval_every, de.patience),
        ">= 1 each",
    )
    c(
        de.encode_batch >= 0,
        where,
        "[descriptor] encode_batch",
        de.encode_batch,
        ">= 0 (0: automatic)",
    )
    for key in ("epochs", "batch_size", "max_train_subimages", "shard_frames"):
        c(getattr(de, key) >= 1, where, f"[descriptor] {key}", getattr(de, key), ">= 1")
    c(de.num_workers >= 0, where, "[descriptor] num_workers", de.num_workers, ">= 0")
    c(de.prefetch >= 0, where, "[descriptor] prefetch", de.prefetch, ">= 0")
    c(de.crop_threads >= 0, where, "[descriptor] crop_threads", de.crop_threads, ">= 0")
    c(
        de.input_size >= 8 and de.input_size % 8 == 0,
        where,
        "[descriptor] input_size",
        de.input_size,
        "a multiple of 8, >= 8 pixels",
    )
    c(de.lr > 0, where, "[descriptor] lr", de.lr, "> 0")
    c(de.gem_p > 0, where, "[descriptor] gem_p", de.gem_p, "> 0")
    c(all(v > 0 for v in de.std), where, "[descriptor] std", list(de.std), "three values > 0")
    check_network_file(de, where)
    c(
        all(ch >= 1 for ch in de.channels),
        where,
        "[descriptor] channels",
        list(de.channels),
        "three integers >= 1",
    )


def check_network_file(de: DescriptorConfig, where: str) -> None:
    """A user's network (``torchscript``, ``onnx``) is a local file: nothing is downloaded."""
    if de.name in ("torchscript", "onnx"):
        check_value(bool(de.path), where, "[descriptor] path", de.path, f"the local {de.name} file")
        check_value(
            Path(de.path).is_file(),
            where,
            "[descriptor] path",
            de.path,
            "an existing file (nothing is downloaded at run time)",
        )


def check_projection(pj: ProjectionConfig, where: str) -> None:
    """``[projection]``: its dimension and the samples it is fitted on."""
    c = check_value
    c(pj.dim >= 0, where, "[projection] dim", pj.dim, ">= 0 (0: the full descriptor)")
    c(
        pj.fit_samples >= max(pj.dim, 1),
        where,
        "[projection] fit_samples",
        pj.fit_samples,
        f">= dim ({pj.dim}) and >= 1",
    )

"""The rank engines' distance kernels: squared L2 by matrix products, fp32 or bf16.

Into buffers kept per thread; each frame's minimum; the error bounds of the expansion.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np
import torch

log = logging.getLogger(__name__)
#: Unit roundoff of float32 (round to nearest).
F32_U = 2.0**-24
#: Unit roundoff of a float32 product's inputs under ``torch.set_float32_matmul_precision``:
#: "high" lets a product round its inputs to TF32 (10-bit fraction), "medium" to bfloat16.
MATMUL_INPUT_U = {"highest": 0.0, "high": 2.0**-11, "medium": 2.0**-8}
#: Unit roundoff of bfloat16 (8 significant bits, round to nearest).
BF16_U = 2.0**-8


_local = threading.local()


def workspace(name: str, numel: int, device: torch.device) -> torch.Tensor:
    """A flat float32 buffer of at least ``numel`` elements, kept for the calling thread.

    A fresh buffer of tens of megabytes pays a page fault per 4 KiB on first touch, which
    costs a small ranking call as much as a tenth of its matrix products; reused, it costs
    nothing. The buffer grows to the largest size asked and lives as long as the thread. Device
    memory is not kept: a CUDA buffer is allocated per call.
    """
    if device.type != "cpu":
        return torch.empty(max(numel, 1), dtype=torch.float32, device=device)[:numel]
    bufs: dict[tuple[str, str], torch.Tensor] = _local.__dict__.setdefault("bufs", {})
    key = (name, str(device))
    buf = bufs.get(key)
    if buf is None or buf.numel() < numel:
        buf = bufs[key] = torch.empty(max(numel, 1), dtype=torch.float32, device=device)
    return buf[:numel]


def scratch(name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """:func:`workspace` for numpy: an uninitialised array of ``shape``, kept for the thread."""
    bufs: dict[str, np.ndarray] = _local.__dict__.setdefault("arrays", {})
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buf = bufs.get(name)
    if buf is None or buf.nbytes < nbytes:
        buf = bufs[name] = np.empty(max(nbytes, 1), np.uint8)
    out: np.ndarray = buf[:nbytes].view(dtype).reshape(shape)
    return out


def expansion_error_factor(dim: int) -> float:
    """``c`` with ``|v - |q - b|^2| <= c (|q| + |b|)^2`` for the fast value ``v`` of any pair.

    ``v = fl(fl(qn + bn) - 2 fl(q.b))`` (clamped at 0), where ``qn``, ``bn`` are the float32
    squared norms. A float32 dot product of ``dim`` terms, summed in any order, is off by at most
    ``g_dim sum |q_i b_i| <= g_dim |q||b|`` (``g_n = n u / (1 - n u)``, Higham, Accuracy and
    Stability of Numerical Algorithms, 3.1); each norm by ``g_(dim+3) |.|^2`` (sum, square root,
    square), and the two additions add ``u`` of their operands each. All of it is below
    ``g_(dim+8) (|q| + |b|)^2``, with ``|q|`` taken from its float32 value (a relative ``g``
    larger at most: the divisor ``1 - 2g`` covers it). A product whose inputs may be rounded
    (TF32, bfloat16: :data:`MATMUL_INPUT_U`) adds ``2 u_in |q||b|``. ``inf`` where ``dim`` is so
    large that the bound says nothing (every row of the place is then measured).
    """
    nu = (dim + 8) * F32_U
    if nu >= 0.25:
        return float("inf")
    g = nu / (1 - nu)
    u_in = MATMUL_INPUT_U.get(torch.get_float32_matmul_precision(), 2.0**-8)
    return (g + 2 * u_in) / (1 - 2 * g) * (1 + 1e-6)


def bf16_error_factor(dim: int) -> float:
    """:func:`expansion_error_factor`'s ``c`` for a bfloat16 product of float32 vectors.

    The product rounds each input to bfloat16 (``|q~ . b~ - q . b| <= (2u + u^2) |q||b|``,
    ``u`` = :data:`BF16_U`), accumulates in float32 (``g_dim`` of the rounded inputs, at most
    ``(1 + u)^2`` larger) and, on CPU, rounds the dot product to bfloat16 (``u`` of it). Twice
    that error (the expansion's ``-2 q.b``), with ``|q||b| <= (|q| + |b|)^2 / 4``, is added to the
    float32 expansion's own ``c`` (norms and additions in float32). The vectors are first
    centred (``q - m``, ``b - m`` in float32, norms taken of the centred ones): each centred vector
    is within ``u32 |.|`` of its exact value, which moves the squared distance by at most
    ``3 u32 (|q| + |b|)^2``, also added. ``inf`` where ``dim`` is so large that the bound says
    nothing.
    """
    nu = (dim + 8) * F32_U
    if nu >= 0.25:
        return float("inf")
    g, u = nu / (1 - nu), BF16_U
    dot = (2 * u + u * u) + g * (1 + u) ** 2 + u * (1 + u) ** 2 * (1 + g)
    return (g / (1 - 2 * g) + 2 * dot / 4 + 3 * F32_U) * (1 + 1e-6)


def sqdist_into(
    query: torch.Tensor,
    qn: torch.Tensor,
    block: torch.Tensor,
    bn: torch.Tensor,
    out: torch.Tensor,
    clamp: bool = True,
) -> torch.Tensor:
    """Squared L2 distances by the expansion, written into ``out`` (no allocation), clamped at 0.

    float32 operands: the product is added into ``out`` in place. bfloat16 operands (the bf16
    candidate product): the norms stay float32, the product accumulates in float32 (CUDA's
    reduced-precision reduction is turned off for the call) and its bfloat16 result is widened
    into ``out``. ``clamp=False`` leaves the clamp to the caller: a minimum clamped is the clamped
    values' minimum, so a caller that keeps only minima clamps 16x fewer values.
    """
    torch.add(qn, bn[None, :], out=out)
    if query.dtype != torch.bfloat16:
        out.addmm_(query, block.T, alpha=-2.0)
    elif query.device.type == "cuda":
        flag = torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction
        torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction = False
        try:
            out.add_(query @ block.T, alpha=-2.0)
        finally:
            torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction = flag
    else:
        out.add_(query @ block.T, alpha=-2.0)
    return out.clamp_min_(0) if clamp else out


def frame_min(d2: torch.Tensor, lens: np.ndarray, idx: torch.Tensor | None) -> torch.Tensor:
    """(n, k) minimum of ``d2``'s columns over each of k frames of ``lens`` rows (in order).

    ``idx``: None where every frame has the same length; otherwise :func:`pad_index`'s columns.
    On the CPU numpy's ``take`` gathers them, in half the time of torch's ``index_select`` (17 ms
    against 36 ms for 1,024 queries over 7,000 rows in frames of 5 to 16 rows, measured): the same
    values, so the same minima.
    """
    n, k = d2.shape[0], len(lens)
    if k == 0:
        return torch.full((n, 0), float("inf"), dtype=torch.float32, device=d2.device)
    width = int(lens.max())
    if idx is None:
        return _last_min(d2.view(n, k, width))
    if d2.device.type == "cpu" and d2.is_contiguous():
        padded = torch.from_numpy(np.take(d2.numpy(), idx.numpy(), axis=1))
    else:
        padded = torch.index_select(d2, 1, idx)
    return _last_min(padded.view(n, k, width))


def _last_min(x: torch.Tensor) -> torch.Tensor:
    """``x.amin(2)`` of a contiguous (n, k, w) tensor.

    An even ``w`` is first halved by the elementwise minimum of its two halves, which runs in full
    vectors (6-8 ms against 8.5-9 ms for 1,024 x 512 frames of 16 rows, measured): the minimum of
    the same values either way.
    """
    n, k, w = x.shape
    if w < 4 or w % 2:
        return x.amin(2)
    halves = x.view(n, k, 2, w // 2)
    return torch.minimum(halves[:, :, 0], halves[:, :, 1]).amin(2)


def pad_index(lens: np.ndarray, device: torch.device) -> torch.Tensor | None:
    """Columns padding each frame's rows to the longest with repeats of its last row.

    A repeat leaves the minimum as it is. None where the frames are of one length (a reshape does).
    """
    if len(lens) == 0 or int(lens.min()) == int(lens.max()):
        return None
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    offs = np.minimum(np.arange(int(lens.max()))[None, :], lens[:, None] - 1)
    return torch.from_numpy((starts[:, None] + offs).ravel()).to(device)


def frame_min_sqdist_chunk(
    query: torch.Tensor, qn: torch.Tensor, block: torch.Tensor, lengths: torch.Tensor
) -> torch.Tensor:
    """(n, k) smallest squared L2 distance from each query to each of k frames in ``block``.

    ``block`` holds the frames' rows one frame after another (``lengths`` rows each). The minimum
    over a frame's rows is a reshape and ``amin``: frames of equal length need no copy; otherwise
    each frame's rows are padded to the longest with repeats of its last row, one gather of the
    product's columns. Exact: the same minima as any other order of the same values.
    """
    bn = torch.linalg.vector_norm(block, dim=1).square_()  # fused: no (rows x D) temporary
    out = torch.empty((query.shape[0], block.shape[0]), dtype=torch.float32, device=query.device)
    lens = lengths.cpu().numpy().astype(np.int64)
    d2 = sqdist_into(query, qn, block, bn, out)
    return frame_min(d2, lens, pad_index(lens, query.device))

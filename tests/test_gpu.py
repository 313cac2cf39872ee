"""The CUDA path (``gpu`` marker).

Skipped where no CUDA device is present, run by ``pytest -m gpu``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from harness.retrieval import Engine, image_ranks

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine"),
]


def test_cuda_ranks_equal_cpu_ranks_up_to_float_ties() -> None:
    rng = np.random.default_rng(0)
    db = rng.standard_normal((20_000, 256)).astype(np.float32)
    db = (db / np.linalg.norm(db, axis=1, keepdims=True)).astype(np.float16)
    frame = np.repeat(np.arange(1250), 16)
    q = db[rng.choice(len(db), 3000)].astype(np.float32) + 0.05 * rng.standard_normal(
        (3000, 256)
    ).astype(np.float32)
    gt = frame[rng.choice(len(db), 3000)]
    place = [np.array([g, min(g + 1, 1249)]) for g in gt]
    cpu = image_ranks(q, db, frame, gt, place, engine=Engine(device="cpu"))
    gpu = image_ranks(q, db, frame, gt, place, engine=Engine(device="cuda"))
    np.testing.assert_array_equal(cpu[1], gpu[1])  # L
    np.testing.assert_allclose(cpu[2], gpu[2], rtol=1e-6)  # d is recomputed exactly on the host
    differ = np.nonzero(cpu[0] != gpu[0])[0]
    assert len(differ) <= 3, (
        f"{len(differ)} ranks differ"
    )  # only where two frames' distances tie within float32
    assert np.all(np.abs(cpu[0][differ] - gpu[0][differ]) <= 1)

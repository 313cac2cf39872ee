"""Decoding no more than the crops need (issue 37): a frame at 1/2, 1/4 or 1/8 where boxes allow.

The reduced path's crops and descriptors against the full frame's, on NCLT-sized frames written
as JPEG and as PNG by the test; the tolerance is stated in ``docs/decisions.md`` (*Reduced decode*).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from harness.descriptors.crops import iter_crops, levels, reduction
from harness.imagestore import read_image


def _frame(tmp: Path, suffix: str) -> str:
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (1616, 1232, 3), dtype=np.uint8), (0, 0), 6)
    p = tmp / f"f{suffix}"
    cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix == ".jpg" else [])
    return str(p)


def test_the_reduction_keeps_every_box_at_the_input_size() -> None:
    boxes = np.array([[0, 0, 600, 900], [100, 100, 700, 1200]], float)
    assert reduction(boxes, 256) == 2  # 600 / 2 = 300 >= 256; / 4 = 150 < 256
    assert reduction(boxes, 64) == 8
    assert reduction(np.array([[0, 0, 200, 900]], float), 256) == 1  # 200 < 256: full frame
    assert reduction(np.zeros((0, 4)), 256) == 1
    from harness.proposals.builtin import grid5

    # grid5 on an NCLT frame: the centre box (410 x 538) at full scale, the others at 1/2
    assert levels(grid5(1232, 1616), 256).tolist() == [1, 2, 2, 2, 2]
    assert levels(grid5(1232, 1616), 64).tolist() == [4, 8, 8, 8, 8]


def test_a_reduced_frame_has_the_size_and_pixels_of_the_full_one_shrunk(tmp_path: Path) -> None:
    for suffix in (".jpg", ".png"):
        uri = _frame(tmp_path, suffix)
        full = read_image(uri)
        for f in (2, 4, 8):
            small = read_image(uri, f)
            assert small.shape == (-(-1616 // f), -(-1232 // f), 3)
            ref = cv2.resize(full, small.shape[1::-1], interpolation=cv2.INTER_AREA)
            # libjpeg's DCT scaling is not an area average: within 2 grey levels on average
            assert np.abs(small.astype(int) - ref).mean() < (2.0 if suffix == ".jpg" else 1e-9)


def test_reduced_crops_and_descriptors_equal_the_full_frames_within_the_tolerance(
    tmp_path: Path,
) -> None:
    from harness.proposals.builtin import grid5

    rows = []
    rng = np.random.default_rng(1)
    for suffix in (".jpg", ".png"):
        uri = _frame(tmp_path, suffix)
        for _ in range(6):  # grid5-sized boxes: every one at least 2 x 256 on each side
            x1, y1 = rng.uniform(0, 300), rng.uniform(0, 400)
            rows.append((uri, x1, y1, x1 + rng.uniform(520, 900), y1 + rng.uniform(520, 1200)))
        rows += [(uri, *b) for b in grid5(1232, 1616)]  # levels 1 and 2 in one frame
    df = pd.DataFrame(rows, columns=["image", "x1", "y1", "x2", "y2"])

    def crops(reduced: bool) -> np.ndarray:
        got = list(iter_crops(df, df["image"], 256, reduced=reduced))
        return np.concatenate([c for _, c in got]).astype(np.float64)

    full, red = crops(False), crops(True)
    assert full.shape == red.shape == (22, 256, 256, 3)
    diff = np.abs(full - red)
    assert diff.mean() < 2.0 and np.percentile(diff, 99) < 12  # grey levels of 255
    import torch

    from harness.descriptors.autoencoder import ConvAutoencoder, inference_encoder, to_tensor

    torch.manual_seed(0)  # the paper's encoder, random weights: the function the descriptors use
    enc = inference_encoder(ConvAutoencoder().eval())
    with torch.no_grad():
        a, b = (
            enc(to_tensor(x.astype(np.uint8), torch.device("cpu"))).numpy() for x in (full, red)
        )
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    assert (a * b).sum(1).min() > 0.999  # cosine of each crop's descriptor with its full twin


# ------------------------------------------------ decode ahead of the encoder (a reader thread)


def test_prefetched_keeps_the_order_raises_where_the_producer_failed_and_stops_when_left() -> None:
    import threading

    import pytest

    from harness.runtime.prefetch import prefetched

    assert list(prefetched(iter(range(50)), 3)) == list(range(50))
    assert list(prefetched(iter(range(5)), 0)) == list(range(5))

    def broken():
        yield 1
        yield 2
        raise ValueError("frame 3 is unreadable")

    got = []
    with pytest.raises(ValueError, match="frame 3"):
        for x in prefetched(broken(), 2):
            got.append(x)
    assert got == [1, 2]  # every item before the failure, then the producer's own error
    produced = []

    def endless():
        i = 0
        while True:
            produced.append(i)
            yield i
            i += 1

    it = prefetched(endless(), 2)
    assert [next(it) for _ in range(3)] == [0, 1, 2]
    it.close()  # the consumer leaves: the reader stops, it does not run on
    n = len(produced)
    assert n <= 3 + 2 + 1 and not [t for t in threading.enumerate() if t.name == "prefetch"]


def test_descriptors_are_the_same_bytes_with_and_without_the_reader_thread(
    tmp_path: Path,
) -> None:
    """``[descriptor] prefetch`` and ``crop_threads`` change when and where frames are decoded,
    never what is encoded (12 frames in 8-frame batches: a full batch and a short one)."""
    from harness.descriptors.config import DescriptorConfig
    from harness.descriptors.extract import encode_shard

    rng = np.random.default_rng(2)
    frames, rows = [], []
    for i in range(12):
        p = tmp_path / f"{i}.jpg"
        img = cv2.GaussianBlur(rng.integers(0, 256, (160, 120, 3), dtype=np.uint8), (0, 0), 2)
        cv2.imwrite(str(p), img)
        frames.append(("s", "Cam5", i, str(p)))
        for b in range(3):
            x1, y1 = rng.uniform(0, 50), rng.uniform(0, 70)
            rows.append(("s", "Cam5", i, "grid5", b, x1, y1, x1 + 60, y1 + 80))
    fr = pd.DataFrame(frames, columns=["session", "camera", "utime", "image"])
    df = pd.DataFrame(
        rows,
        columns=["session", "camera", "utime", "proposal_method", "box_id", "x1", "y1", "x2", "y2"],
    )
    out = {}
    for depth, threads in ((0, 1), (2, 1), (0, 3), (2, 0)):
        dc = DescriptorConfig(
            name="thumb", input_size=32, prefetch=depth, shard_frames=4, crop_threads=threads
        )
        d = tmp_path / f"p{depth}t{threads}"
        d.mkdir()
        encode_shard(dc, d, None, fr, df, f"prefetch {depth}", d)
        out[depth, threads] = np.load(d / "desc.npy")
    one = out[0, 1]
    assert one.shape == (36, one.shape[1]) and one.shape[1] > 0
    assert all(v.tobytes() == one.tobytes() for v in out.values())

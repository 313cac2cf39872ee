"""Cropping proposal boxes out of frames and resizing them, in batches.

Through a torch DataLoader or a pool of threads. One dataset item is one frame: it is decoded
once and all its boxes are cropped and resized with OpenCV. With ``num_workers > 0`` decoding
overlaps the consumer's compute; with threads, a batch's frames are decoded side by side. Order
is preserved, so results depend on neither.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pandas as pd
import torch
from torch.utils.data import DataLoader, Dataset

from harness.imagestore import read_image
from harness.runtime.prefetch import prefetched


def crop_resize(rgb: np.ndarray, boxes: np.ndarray, size: int) -> np.ndarray:
    """Crop ``boxes`` (k, 4; float pixels, x2/y2 exclusive) and resize each to ``size`` x ``size``.

    The crop covers every pixel the box touches (floor of the start, ceil of the end), at least
    one pixel. Returns uint8 (k, size, size, 3).
    """
    h, w = rgb.shape[:2]
    out = np.empty((len(boxes), size, size, 3), np.uint8)
    for i, (x1, y1, x2, y2) in enumerate(np.asarray(boxes, np.float64)):
        a, b = int(np.clip(np.floor(x1), 0, w - 1)), int(np.clip(np.floor(y1), 0, h - 1))
        c, d = int(np.clip(np.ceil(x2), a + 1, w)), int(np.clip(np.ceil(y2), b + 1, h))
        patch = rgb[b:d, a:c]
        interp = (
            cv2.INTER_AREA if (patch.shape[0] > size or patch.shape[1] > size) else cv2.INTER_LINEAR
        )
        out[i] = cv2.resize(patch, (size, size), interpolation=interp)
    return out


def levels(boxes: np.ndarray, size: int) -> np.ndarray:
    """Each box's pyramid level: the largest of 8, 4, 2 that leaves it ``size`` pixels a side, or 1.

    Cropped from the frame shrunk by that factor, a box is still shrunk (never enlarged) to
    ``size``, so its crop is the full frame's up to the resampling (``docs/method.md``).
    """
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    side = np.minimum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
    out = np.ones(len(b), np.int64)
    for f in (2, 4, 8):
        out[side / f >= size] = f
    return out


def reduction(boxes: np.ndarray, size: int) -> int:
    """The fraction the frame can be decoded at: its boxes' smallest level (1 without boxes)."""
    lv = levels(boxes, size)
    return int(lv.min()) if len(lv) else 1


def crop_pyramid(uri: str, boxes: np.ndarray, size: int) -> np.ndarray:
    """The crops of ``boxes``, each from the coarsest frame of a pyramid that its level allows.

    The frame is decoded at :func:`reduction` (a JPEG at 1/2, 1/4 or 1/8: less decoding), then
    halved (area average) for the boxes of coarser levels: a large box is resized from a small
    frame, not from the full one.
    """
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    lv = levels(b, size)
    f0 = int(lv.min()) if len(lv) else 1
    img = read_image(uri, f0)
    out = np.empty((len(b), size, size, 3), np.uint8)
    f = f0
    while True:
        sel = lv == f
        if sel.any():
            out[sel] = crop_resize(img, b[sel] / f, size)
        if not (lv > f).any():
            return out
        h, w = img.shape[:2]
        img = cv2.resize(img, (-(-w // 2), -(-h // 2)), interpolation=cv2.INTER_AREA)
        f *= 2


class _FrameCrops(Dataset):
    def __init__(
        self, groups: list[tuple[str, np.ndarray, np.ndarray]], size: int, reduced: bool
    ) -> None:
        self.groups = groups
        self.size = size
        self.reduced = reduced

    def __len__(self) -> int:
        return len(self.groups)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        uri, rows, boxes = self.groups[i]
        if self.reduced:
            return rows, crop_pyramid(uri, boxes, self.size)
        return rows, crop_resize(read_image(uri), boxes, self.size)


def _collate(items: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    return np.concatenate([r for r, _ in items]), np.concatenate([c for _, c in items])


def _threaded(
    frames: _FrameCrops, frames_per_batch: int, threads: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The loader's batches (``frames_per_batch`` frames in order), decoded by ``threads`` threads.

    Each frame is decoded and cropped by one thread: otherwise the decode and the area resizes
    run on one core while the encoder's other threads wait (1.8 ms against 1.15 ms a 256 x 256
    subimage on 2 cores, measured).
    """
    with ThreadPoolExecutor(threads, thread_name_prefix="crops") as pool:
        for s in range(0, len(frames), frames_per_batch):
            items = range(s, min(s + frames_per_batch, len(frames)))
            yield _collate(list(pool.map(frames.__getitem__, items)))


#: Frames a batch holds, by default: :func:`iter_crops`' and :func:`crop_jobs`' alike, so both give
#: their caller the same batches (numpy's product in a projection gives other last bits for a
#: batch of other rows).
FRAMES_PER_BATCH = 8
#: A batch of crops and the job that makes it: (its rows, the function).
CropJob = tuple[int, Callable[[], tuple[np.ndarray, np.ndarray]]]


def _groups(boxes: pd.DataFrame, images: pd.Series) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Each frame's (image URI, row positions, boxes (k, 4)), in the rows' order."""
    uris = images.to_numpy()
    b = boxes[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    starts = (
        np.concatenate([[0], np.nonzero(uris[1:] != uris[:-1])[0] + 1, [len(uris)]])
        if len(uris)
        else np.zeros(1, int)
    )
    return [(str(uris[s]), np.arange(s, e), b[s:e]) for s, e in itertools.pairwise(starts)]


def crop_jobs(
    boxes: pd.DataFrame,
    images: pd.Series,
    size: int,
    frames_per_batch: int = FRAMES_PER_BATCH,
    reduced: bool = False,
) -> list[CropJob]:
    """:func:`iter_crops`' batches as functions, in order, each with its number of rows.

    Each decodes and crops its frames when it is called, in whichever thread calls it, and
    returns the batch's ``(row positions, crops)``.
    """
    frames = _FrameCrops(_groups(boxes, images), size, reduced)

    def job(items: range) -> CropJob:
        rows = sum(len(frames.groups[i][1]) for i in items)
        return rows, lambda: _collate([frames[i] for i in items])

    return [
        job(range(s, min(s + frames_per_batch, len(frames))))
        for s in range(0, len(frames), frames_per_batch)
    ]


def iter_crops(
    boxes: pd.DataFrame,
    images: pd.Series,
    size: int,
    frames_per_batch: int = FRAMES_PER_BATCH,
    num_workers: int = 0,
    reduced: bool = False,
    prefetch: int = 0,
    threads: int = 1,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield ``(row positions, crops uint8 (b, size, size, 3))`` for the rows of ``boxes``.

    Args:
        boxes: rows with ``x1, y1, x2, y2`` and a frame key; rows of one frame must be contiguous.
        images: image URI per row of ``boxes`` (aligned).
        size: output side in pixels.
        frames_per_batch: frames decoded per batch (rows of one frame are never split).
        num_workers: DataLoader processes decoding and cropping (0: in this process).
        reduced: each box from the coarsest level of a frame pyramid it allows, the frame decoded
            at the finest level needed (:func:`crop_pyramid`; ``[descriptor] decode =
            "reduced"``).
        prefetch: batches a reader thread decodes ahead of the consumer
            (:func:`harness.runtime.prefetch.prefetched`); ignored with ``num_workers`` > 0, where
            the loader's processes decode ahead.
        threads: threads that decode and crop a batch's frames side by side (0: torch's
            intra-op thread count); ignored with ``num_workers`` > 0. The same batches, in the
            same order, whatever the number.
    """
    groups = _groups(boxes, images)
    threads = threads if threads > 0 else torch.get_num_threads()
    if num_workers == 0 and threads > 1:
        batches = _threaded(_FrameCrops(groups, size, reduced), frames_per_batch, threads)
        yield from prefetched(batches, prefetch)
        return
    loader = DataLoader(
        _FrameCrops(groups, size, reduced),
        batch_size=frames_per_batch,
        shuffle=False,
        num_workers=num_workers,
        collate_fn=_collate,
        persistent_workers=False,
        prefetch_factor=2 if num_workers else None,
        generator=torch.Generator().manual_seed(0),
    )
    yield from prefetched(loader, 0 if num_workers else prefetch)

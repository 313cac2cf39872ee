"""The descriptor stages' units (method §6).

Training crops and the model, encoding shards, combining a session's shards. Each is a function of
typed inputs to files in a temporary entry directory (the runner caches it); none reads the config
beyond ``[descriptor]``.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from harness.descriptors import store
from harness.descriptors.base import Descriptor, make_descriptor, normalize
from harness.descriptors.config import DescriptorConfig, ProjectionConfig
from harness.descriptors.crops import CropJob, crop_jobs, iter_crops
from harness.descriptors.projection import fit_projection, load_projection, project
from harness.errors import HarnessError, RetrievalError
from harness.records import FRAME_KEY
from harness.runtime.cache import open_memmap_reserved, read_cached_parquet, write_parquet
from harness.runtime.progress import progress, progress_bar

log = logging.getLogger(__name__)

#: torch's threads while a model trains. The weights' last bits depend on the thread count (on
#: the fixture one thread trains 978b9a45b447dc88, two 978dd804b216655a: measured), so every
#: machine trains with the two that every machine of this project's kind has, whatever its cores
#: or OMP_NUM_THREADS (the same tables everywhere).
TRAIN_THREADS = 2


@contextlib.contextmanager
def torch_threads(n: int = TRAIN_THREADS) -> Iterator[None]:
    """Set torch's intra-op threads to ``n`` for the block; restore them after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _images(rows: pd.DataFrame, frames: pd.DataFrame) -> pd.Series:
    """The image URI of each proposal row's frame, aligned with ``rows``."""
    return rows.merge(frames[[*FRAME_KEY, "image"]], on=FRAME_KEY, how="left")["image"]


def train_model(
    dc: DescriptorConfig, frames: pd.DataFrame, rows: pd.DataFrame, tmp: Path
) -> dict[str, Any]:
    """Train the descriptor on crops of ``rows``.

    At most ``max_train_subimages`` crops are drawn (with ``seed``).

    The crops go to a memmap in ``tmp`` (removed after training), so memory does not grow with
    the sample. Descriptors that need no training write nothing.

    Args:
        dc: ``[descriptor]``.
        frames: The frame table (for image URIs).
        rows: Proposal rows of every session (the training pool).
        tmp: The model entry's directory.

    Returns:
        The training record (losses, steps, stop reason) kept in the entry's manifest.
    """
    desc = make_descriptor(dc)
    if not desc.needs_training:
        return {"trained": False}
    rng = np.random.default_rng(dc.seed)
    n = min(len(rows), dc.max_train_subimages)
    rows = rows.iloc[np.sort(rng.choice(len(rows), size=n, replace=False))].reset_index(drop=True)
    data = open_memmap_reserved(
        tmp / "train_crops.npy", np.uint8, (n, dc.input_size, dc.input_size, 3)
    )
    for idx, crops in progress(
        iter_crops(
            rows,
            _images(rows, frames),
            dc.input_size,
            num_workers=dc.num_workers,
            reduced=dc.decode == "reduced",
            prefetch=dc.prefetch,
            threads=dc.crop_threads,
        ),
        "training crops",
        "batch",
    ):
        data[idx] = crops
    data.flush()
    parts = store.training_parts(dc, data, TRAIN_THREADS)
    digest = store.training_digest(parts)
    kept = store.load_kept(dc.trained_models, digest, tmp)
    if kept is not None:  # this very training was done before: its model, not a new one
        del data
        (tmp / "train_crops.npy").unlink()
        store.write_record(tmp, digest, parts, kept["info"])
        log.info("model %s: kept in %s, not trained again", digest, dc.trained_models)
        return {**kept["info"], "trained_models": digest}
    steps_per_epoch = int(np.ceil(n / dc.batch_size))
    total = (
        int(np.ceil(dc.train_samples / dc.batch_size))
        if dc.train_samples > 0
        else dc.epochs * steps_per_epoch
    )
    bar = progress_bar(total, "autoencoder training", "step")
    with torch_threads():
        info = desc.fit(data, tmp, progress=bar.update)
    bar.close()
    del data
    (tmp / "train_crops.npy").unlink()
    store.write_record(tmp, digest, parts, info)
    return info


def _loaded(dc: DescriptorConfig, model_dir: Path) -> Descriptor:
    desc = make_descriptor(dc)
    if desc.needs_training:
        desc.load(model_dir)
    return desc


def _encoded(
    desc: Descriptor, dc: DescriptorConfig, frames: pd.DataFrame, rows: pd.DataFrame, name: str
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(row positions in ``rows``, L2-normalised float32 descriptors), batch by batch.

    Where the descriptor encodes in lanes (:func:`_lanes`), each lane decodes, crops and encodes
    whole batches with one torch thread; otherwise the batch's frames are decoded side by side,
    then encoded with all of torch's threads. The same descriptors in the same order either way.
    """
    img = _images(rows, frames)
    # frames must be contiguous for the loader: order by frame, remember the original row
    order = np.lexsort(
        (rows["box_id"].to_numpy(), rows["proposal_method"].to_numpy(), rows["utime"].to_numpy())
    )
    rows_o, img_o, reduced = rows.iloc[order], img.iloc[order], dc.decode == "reduced"
    lanes = _lanes(desc, dc)
    if lanes > 1:
        jobs = crop_jobs(rows_o, img_o, dc.input_size, reduced=reduced)
        batches: Iterable[tuple[np.ndarray, np.ndarray]] = _in_lanes(desc, jobs, lanes)
    else:
        batches = (
            (idx, normalize(desc.encode(crops)))
            for idx, crops in iter_crops(  # with prefetch: the next batches decoded meanwhile
                rows_o,
                img_o,
                dc.input_size,
                num_workers=dc.num_workers,
                reduced=reduced,
                prefetch=dc.prefetch,
                threads=dc.crop_threads,
            )
        )
    for idx, v in progress(batches, f"descriptors {name}", "batch"):
        yield order[idx], v


#: Descriptors encoded in lanes on CPU (:func:`_in_lanes`): a convolution in one thread computes
#: every output as all of torch's threads do, so the descriptors are the same bytes (the fixture's
#: stage records, tested), and the lanes keep the decoding and the encoder on every core.
LANE_DESCRIPTORS = ("autoencoder",)


def _lanes(desc: Descriptor, dc: DescriptorConfig) -> int:
    """How many lanes encode ``desc`` (1: one batch at a time).

    Torch's intra-op threads for a descriptor of :data:`LANE_DESCRIPTORS` on CPU with no loader
    processes.
    """
    device = getattr(desc, "device", None)
    on_cpu = device is not None and getattr(device, "type", "") == "cpu"
    if dc.num_workers > 0 or desc.name not in LANE_DESCRIPTORS or not on_cpu:
        return 1
    return torch.get_num_threads()


#: Subimages a group of batches holds at most (the paper's 16,384 float32 values each: 128 MiB).
LANE_GROUP_ROWS = 2048


def _in_lanes(
    desc: Descriptor, jobs: list[CropJob], lanes: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Each batch of ``jobs`` decoded, cropped and encoded in one of ``lanes`` threads.

    Torch's intra-op threads are one meanwhile. The batches run in groups of at most
    :data:`LANE_GROUP_ROWS` subimages and a group's batches come out, in order, once all of them
    are encoded: what the caller does with them (the projection, numpy's BLAS on its own threads)
    then has the cores to itself. Beside two busy lanes a projection's product took 8x its time
    (11.6 ms against 1.4 ms a batch of 40 subimages; beside one busy thread, 2.1 ms).

    On CPU one thread a batch keeps both the decoding and the encoder's layers on every core,
    where all the threads on one batch wait for each other between its steps.
    """

    def one(job: CropJob) -> tuple[np.ndarray, np.ndarray]:
        idx, crops = job[1]()
        return idx, normalize(desc.encode(crops))

    size = desc.input_size
    desc.encode(np.zeros((0, size, size, 3), np.uint8))  # builds its encoder here, once
    groups: list[list[CropJob]] = [[]]
    rows = 0
    for job in jobs:
        if groups[-1] and rows + job[0] > LANE_GROUP_ROWS:
            groups.append([])
            rows = 0
        groups[-1].append(job)
        rows += job[0]
    with torch_threads(1), ThreadPoolExecutor(lanes, thread_name_prefix="encode") as pool:
        for group in groups:
            yield from list(pool.map(one, group))


def fit_projection_unit(
    dc: DescriptorConfig,
    pc: ProjectionConfig,
    model_dir: Path,
    frames: pd.DataFrame,
    rows: pd.DataFrame,
    tmp: Path,
) -> dict[str, Any]:
    """Fit ``[projection]`` on a seeded sample of the reference ``rows``, encoded here.

    At most ``fit_samples`` rows are drawn.

    Memory: the sample, ``fit_samples x D`` float32 (512 MiB at 8,192 x 16,384).

    Args:
        dc: ``[descriptor]``.
        pc: ``[projection]``.
        model_dir: The trained model.
        frames: The frame table (image URIs).
        rows: The reference sessions' proposal rows.
        tmp: The entry's directory (see :func:`harness.descriptors.projection.fit_projection`).

    Returns:
        The fit record (rows sampled, dims, explained variance).
    """
    pick = np.sort(
        np.random.default_rng(pc.seed).choice(
            len(rows), size=min(len(rows), pc.fit_samples), replace=False
        )
    )
    rows = rows.iloc[pick].reset_index(drop=True)
    sample = None
    for pos, v in _encoded(_loaded(dc, model_dir), dc, frames, rows, "projection sample"):
        if sample is None:
            sample = np.empty((len(rows), v.shape[1]), np.float32)
        sample[pos] = v
    if sample is None:
        raise RetrievalError(
            "[projection] the reference sessions have no subimage to fit the projection on"
        )
    return {"reference_rows": len(pick), **fit_projection(pc, sample, tmp)}


def encode_shard(
    dc: DescriptorConfig,
    model_dir: Path,
    projection_dir: Path | None,
    frames: pd.DataFrame,
    rows: pd.DataFrame,
    name: str,
    tmp: Path,
) -> dict[str, Any]:
    """Crop, encode, L2-normalise (and project) ``rows`` into ``desc.npy``.

    ``desc.npy`` is aligned with ``index.parquet``.

    Args:
        dc: ``[descriptor]`` (``dtype`` is the stored type).
        model_dir: The model entry (ignored by descriptors that need no training).
        projection_dir: A fitted projection entry, applied before storing; None: the full
            descriptor.
        frames: The session's frames (for image URIs).
        rows: The shard's proposal rows.
        name: What the progress bar calls the shard.
        tmp: The shard entry's directory.

    Returns:
        ``{"subimages": rows, "dim": stored descriptor length}``.
    """
    proj = load_projection(projection_dir) if projection_dir is not None else None
    arr = None
    for pos, v in _encoded(_loaded(dc, model_dir), dc, frames, rows, name):
        if proj is not None:
            v = project(v, *proj)
        bad = ~np.isfinite(v).all(axis=1)
        if bad.any():
            raise HarnessError(
                f"descriptors ({name}): {int(bad.sum())} of {len(v)} subimages have NaN or inf "
                f"descriptors ([descriptor] name = {dc.name!r}); a diverged model or a broken "
                "network ranks nothing: retrain, or check the model"
            )
        if arr is None:
            arr = open_memmap_reserved(tmp / "desc.npy", dc.dtype, (len(rows), v.shape[1]))
        arr[pos] = v.astype(dc.dtype)
    _finish_desc(tmp, arr, dc.dtype)
    write_parquet(tmp / "index.parquet", rows)
    return {"subimages": len(rows), "dim": int(arr.shape[1]) if arr is not None else 0}


def combine_shards(
    dc: DescriptorConfig, rows: pd.DataFrame, shard_dirs: list[Path], tmp: Path
) -> dict[str, Any]:
    """One session's ``desc.npy`` aligned with its proposal ``rows``, copied one shard at a time.

    Args:
        dc: ``[descriptor]`` (the stored dtype).
        rows: The session's proposal rows (the output's row order).
        shard_dirs: The shard entries, each with ``desc.npy`` and ``index.parquet``.
        tmp: The combined entry's directory.

    Returns:
        ``{"subimages", "shards", "dim"}``.
    """
    pos = pd.Series(
        np.arange(len(rows)),
        index=pd.MultiIndex.from_frame(rows[["proposal_method", "utime", "box_id"]]),
    )
    arr = None
    for d in shard_dirs:
        idx = read_cached_parquet(
            d / "index.parquet", columns=["proposal_method", "utime", "box_id"]
        )
        v = np.load(d / "desc.npy", mmap_mode="r")
        if arr is None:
            arr = open_memmap_reserved(tmp / "desc.npy", dc.dtype, (len(rows), v.shape[1]))
        arr[pos.loc[pd.MultiIndex.from_frame(idx)].to_numpy()] = v
    _finish_desc(tmp, arr, dc.dtype)
    write_parquet(tmp / "index.parquet", rows)
    return {
        "subimages": len(rows),
        "shards": len(shard_dirs),
        "dim": int(arr.shape[1]) if arr is not None else 0,
    }


def _finish_desc(tmp: Path, arr: np.memmap | None, dtype: str) -> None:
    """Flush the memmap, or write an empty (0, 1) array when there were no rows."""
    if arr is None:
        np.save(tmp / "desc.npy", np.zeros((0, 1), dtype))
    else:
        arr.flush()

"""The retrieval stage's config: ``[retrieval]``, ``bovw``'s table, ``[import]``, their checks."""

from __future__ import annotations

from dataclasses import dataclass

from harness.checks import check_value


@dataclass(frozen=True)
class RetrievalConfig:
    """``[retrieval]``: the rank engine, the ground-truth place and the database (metres)."""

    engine: str = "exact"  # exact or faiss
    # ground-truth place: reference frames within this radius of G (method §6); 0: G alone
    gt_radius_m: float = 2.0
    # reference database by place: one frame per this many metres of trajectory; 0: every frame
    db_stride_m: float = 0.0
    # database rows the exact engine scores at a time
    chunk_rows: int = 8192
    # query subimages the exact engine ranks at a time
    query_batch: int = 1024
    # exact engine: budget (MiB) of the (queries x frames) matrices per database pass; bounds memory
    # whatever the data size
    memory_mb: float = 1024.0
    faiss_nlist: int = 0  # 0: flat index; >0: IVF with that many lists
    # inverted lists faiss searches (faiss_nlist > 0)
    faiss_nprobe: int = 8
    query_frames_per_shard: int = 512  # pairs per ranking unit (the unit mapped over executors)
    faiss_check: int = 256  # queries per engine also ranked exactly, to report faiss's recall


@dataclass(frozen=True)
class BovwConfig:
    """A bag-of-visual-words localizer (method §11): local features, words, TF-IDF, L1.

    Each subimage is resized to ``input_size`` x ``input_size`` (as the autoencoder's input);
    features are ``sift``, ``rootsift`` or ``orb`` at a dense grid of keypoints (``dense``: every
    ``step`` pixels, diameter ``patch``) or at the detector's own keypoints. ``k`` words are
    learned with faiss k-means on at most ``max_train_features`` features of reference-session
    subimages; IDF from the same subimages.
    """

    # rootsift, sift or orb
    features: str = "rootsift"
    # visual words: the vocabulary's k-means clusters (faiss)
    k: int = 1024
    # features on a dense grid (else at detected keypoints)
    dense: bool = True
    # the dense grid's step, pixels
    step: int = 8
    # the dense features' patch side, pixels
    patch: int = 16
    # the side, pixels, every subimage is resized to
    input_size: int = 128
    # map subimages whose features train the vocabulary, at most
    max_train_subimages: int = 4000
    # features the k-means sees, at most
    max_train_features: int = 200_000
    # k-means iterations
    kmeans_iter: int = 20
    # the vocabulary's draws
    seed: int = 0
    # processes that extract features (0: in the main process)
    num_workers: int = 0
    # frames per cached encoding shard (the unit an interrupted run resumes at)
    shard_frames: int = 256
    # batches of crops a reader thread decodes ahead of the feature extraction (0: none); the
    # features use one core, the thread another (bench case crops: 1.10x)
    prefetch: int = 2


@dataclass(frozen=True)
class ImportConfig:
    """``[import]``: how an imported localizer's rank file is read (method §12)."""

    # what a row's ``scores`` are: "distance" (smaller = more similar) or "similarity" in [0, 1]
    score_kind: str = "distance"
    # a query image of the pairs without any imported row: an error (false), or left out of
    # every table and counted (true)
    allow_unranked_images: bool = False


def check_bovw(bw: BovwConfig, where: str) -> None:
    """Ranges of a ``bovw`` table."""
    c = check_value
    c(bw.features in ("sift", "rootsift", "orb"), where, "features", bw.features,
      "'sift', 'rootsift' or 'orb'")  # fmt: skip
    c(2 <= bw.k <= 1_000_000, where, "k", bw.k, "[2, 1e6]")
    c(bw.step >= 1, where, "step", bw.step, ">= 1")
    c(bw.patch >= 4, where, "patch", bw.patch, ">= 4")
    c(bw.input_size >= 16, where, "input_size", bw.input_size, ">= 16")
    c(bw.max_train_subimages >= 1, where, "max_train_subimages", bw.max_train_subimages, ">= 1")
    c(bw.max_train_features >= bw.k, where, "max_train_features", bw.max_train_features,
      f">= k ({bw.k})")  # fmt: skip
    c(bw.kmeans_iter >= 1, where, "kmeans_iter", bw.kmeans_iter, ">= 1")
    c(bw.seed >= 0, where, "seed", bw.seed, ">= 0")
    c(bw.shard_frames >= 1, where, "shard_frames", bw.shard_frames, ">= 1")
    c(bw.prefetch >= 0, where, "prefetch", bw.prefetch, ">= 0")


def check_retrieval(re_: RetrievalConfig, where: str) -> None:
    """``[retrieval]``: the engine, the place radius against the database stride, sizes."""
    c = check_value
    c(
        re_.engine in ("exact", "faiss"),
        where,
        "[retrieval] engine",
        re_.engine,
        "'exact' or 'faiss'",
    )
    c(
        re_.db_stride_m >= 0,
        where,
        "[retrieval] db_stride_m",
        re_.db_stride_m,
        ">= 0 metres (0: every reference frame)",
    )
    c(
        re_.gt_radius_m >= 0,
        where,
        "[retrieval] gt_radius_m",
        re_.gt_radius_m,
        ">= 0 metres (0: the ground-truth frame alone)",
    )
    for key in ("chunk_rows", "query_batch", "faiss_nprobe", "query_frames_per_shard"):
        c(getattr(re_, key) >= 1, where, f"[retrieval] {key}", getattr(re_, key), ">= 1")
    c(re_.memory_mb > 0, where, "[retrieval] memory_mb", re_.memory_mb, "> 0 MiB")
    for key in ("faiss_nlist", "faiss_check"):
        c(getattr(re_, key) >= 0, where, f"[retrieval] {key}", getattr(re_, key), ">= 0")
    c(
        re_.db_stride_m == 0 or re_.gt_radius_m >= re_.db_stride_m / 2,
        where,
        "[retrieval] gt_radius_m",
        re_.gt_radius_m,
        f"at least half of db_stride_m = {re_.db_stride_m:g} (a place must keep a frame of the "
        "thinned database)",
    )


def check_import(im: ImportConfig, where: str) -> None:
    """``[import]``: what an imported rank file's scores are."""
    check_value(
        im.score_kind in ("distance", "similarity"),
        where,
        "[import] score_kind",
        im.score_kind,
        "'distance' or 'similarity'",
    )

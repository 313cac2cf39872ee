"""The bag-of-visual-words localizer (method §11): the paper's own scene model.

The scheme of DBoW2 and ORB-SLAM's loop closure, built from libraries: local features from
OpenCV (SIFT, RootSIFT or ORB; at a dense grid of keypoints or the detector's own), a vocabulary
of ``k`` words learned with faiss k-means on reference-session subimages only, each subimage a
TF-IDF weighted, L1-normalised word histogram (a row of a ``scipy.sparse`` matrix), and DBoW2's
L1 score ``s(v, w) = 1 - 0.5 |v - w|_1``, which for L1-normalised non-negative vectors equals
``sum_i min(v_i, w_i)`` over the words both hold. Scoring goes through an inverted index (the
database matrix in CSC form: one posting list per word), so no dense subimage x subimage matrix
is ever built; ``dist(q, F) = 1 - max`` over F's subimages of ``s``, and the ranks follow method
section 6 exactly as the descriptor engines' do.

A subimage with no feature gets no vector: it is neither a database row nor a query, and it is
counted (``no_feature_subimages`` in the encoding entry's manifest and ``run.json``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import scipy.sparse as sp

from harness.descriptors.crops import iter_crops
from harness.errors import RetrievalError
from harness.features import extractor
from harness.records import FRAME_KEY
from harness.retrieval.config import BovwConfig
from harness.retrieval.layout import frame_layout, place_columns
from harness.runtime.cache import read_cached_parquet, write_parquet
from harness.runtime.progress import progress

log = logging.getLogger(__name__)

#: A subimage's box: its frame, proposal and coordinates (the crop that gives its features).
BOX_KEY = [*FRAME_KEY, "proposal_method", "box_id", "x1", "y1", "x2", "y2"]
#: The vocabulary's file of its sampled subimages' words.
TRAIN_WORDS = "train_words.parquet"


def _extractor(bc: BovwConfig) -> Any:
    if bc.features == "orb":
        # edgeThreshold/patchSize small enough that a dense grid keeps keypoints near the border
        return extractor("orb", 5000, edgeThreshold=bc.patch, patchSize=bc.patch)
    return extractor("sift")


def grid_keypoints(bc: BovwConfig) -> list[Any]:
    """The dense grid: a keypoint every ``step`` pixels, diameter ``patch``, inside the crop."""
    half = bc.patch / 2
    pts = np.arange(half, bc.input_size - half + 1e-9, bc.step)
    return [cv2.KeyPoint(float(x), float(y), float(bc.patch)) for y in pts for x in pts]


def features(bc: BovwConfig, crops: np.ndarray, extractor: Any = None) -> list[np.ndarray]:
    """Local features of each RGB crop (n, s, s, 3): a float32 (m_i, D) array each (m_i may be 0).

    ORB's 256 bits become 0/1 floats, so k-means and the word assignment work in one metric
    space for every feature type (an L2 approximation of the Hamming distance, documented in
    docs/method.md). RootSIFT: each SIFT vector L1-normalised, then its square root (Arandjelovic
    and Zisserman, 2012).
    """
    ex = extractor if extractor is not None else _extractor(bc)
    grid = grid_keypoints(bc) if bc.dense else None
    out = []
    for crop in crops:
        gray = cv2.cvtColor(np.ascontiguousarray(crop), cv2.COLOR_RGB2GRAY)
        if grid is not None:
            _, desc = ex.compute(gray, list(grid))
        else:
            _, desc = ex.detectAndCompute(gray, None)
        if desc is None or not len(desc):
            dim = 256 if bc.features == "orb" else 128
            out.append(np.zeros((0, dim), np.float32))
            continue
        if bc.features == "orb":
            f = np.unpackbits(desc, axis=1).astype(np.float32)
        else:
            f = desc.astype(np.float32)
            if bc.features == "rootsift":
                f = np.sqrt(f / np.maximum(f.sum(1, keepdims=True), 1e-12))
        out.append(f)
    return out


def _images(rows: pd.DataFrame, frames: pd.DataFrame) -> pd.Series:
    return rows.merge(frames[[*FRAME_KEY, "image"]], on=FRAME_KEY, how="left")["image"]


def iter_features(bc: BovwConfig, rows: pd.DataFrame, frames: pd.DataFrame, name: str) -> Any:
    """(row positions in ``rows``, their features), batch by batch, frames decoded once each."""
    order = np.lexsort(
        (rows["box_id"].to_numpy(), rows["proposal_method"].to_numpy(), rows["utime"].to_numpy())
    )
    img = _images(rows, frames)
    ex = _extractor(bc)
    for idx, crops in progress(
        iter_crops(
            rows.iloc[order],
            img.iloc[order],
            bc.input_size,
            num_workers=bc.num_workers,
            prefetch=bc.prefetch,
        ),
        name,
        "batch",
    ):
        yield order[idx], features(bc, crops, ex)


def train_vocabulary(
    bc: BovwConfig, frames: pd.DataFrame, rows: pd.DataFrame, tmp: Path
) -> dict[str, Any]:
    """Learn ``k`` words (faiss k-means) and their IDF on reference-session subimages ``rows``.

    At most ``max_train_subimages`` subimages (seeded sample) give features; at most
    ``max_train_features`` of those (seeded) enter k-means. IDF of word w is
    ``log(N / n_w)`` over the N sampled subimages with a feature (``n_w``: those holding w; a
    word no sampled subimage holds gets ``log N``). Writes ``vocab.npy`` (k, D) and ``idf.npy``,
    and ``train_words.parquet``: each sampled subimage's box and words (none where it has no
    feature), which :func:`encode_words` reads rather than extracting them again.

    Raises:
        RetrievalError: fewer features than words (``k`` too large for the data).
    """
    import faiss

    rng = np.random.default_rng(bc.seed)
    n = min(len(rows), bc.max_train_subimages)
    pick = np.sort(rng.choice(len(rows), size=n, replace=False)) if n else np.zeros(0, int)
    sample = rows.iloc[pick].reset_index(drop=True)
    feats: list[np.ndarray] = [np.zeros((0, 0), np.float32)] * len(sample)
    for idx, fs in iter_features(bc, sample, frames, "bovw vocabulary features"):
        for i, f in zip(idx, fs, strict=True):
            feats[int(i)] = f
    have = [f for f in feats if len(f)]
    total = sum(len(f) for f in have)
    if total < bc.k:
        raise RetrievalError(
            f"bovw: {total} features in {len(have)} reference subimages, fewer than k = {bc.k} "
            "words; lower k or raise max_train_subimages"
        )
    allf = np.concatenate(have)
    if len(allf) > bc.max_train_features:
        allf = allf[np.sort(rng.choice(len(allf), size=bc.max_train_features, replace=False))]
    km = faiss.Kmeans(
        allf.shape[1], bc.k, niter=bc.kmeans_iter, seed=bc.seed, verbose=False, spherical=False
    )
    km.train(np.ascontiguousarray(allf, np.float32))
    vocab = np.ascontiguousarray(km.centroids, np.float32)
    index = faiss.IndexFlatL2(vocab.shape[1])
    index.add(vocab)
    holds = np.zeros(bc.k, np.int64)
    words = [np.zeros(0, np.int64)] * len(sample)
    for i, f in enumerate(feats):
        if len(f):
            _, w = index.search(np.ascontiguousarray(f, np.float32), 1)
            words[i] = w[:, 0].astype(np.int64)
            holds[np.unique(words[i])] += 1
    idf = np.log(len(have) / np.maximum(holds, 1)).astype(np.float64)
    idf[holds == 0] = np.log(len(have))
    np.save(tmp / "vocab.npy", vocab)
    np.save(tmp / "idf.npy", idf)
    write_parquet(tmp / TRAIN_WORDS, sample[BOX_KEY].assign(words=words))
    return {
        "train_subimages": len(sample),
        "train_subimages_with_features": len(have),
        "features": int(total),
        "kmeans_features": len(allf),
        "k": bc.k,
        "dim": int(vocab.shape[1]),
        "kmeans_objective": float(km.obj[-1]) if km.obj is not None and len(km.obj) else None,
    }


def bow_vectors(words: Sequence[np.ndarray], idf: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """TF-IDF, L1-normalised word histograms of subimages given their words (one array each).

    Returns:
        (CSR matrix (n_with_words, k) float64, positions of the subimages with at least one word).
    """
    k = len(idf)
    keep = np.array([i for i, w in enumerate(words) if len(w)], np.int64)
    indptr, indices, data = [0], [], []
    for i in keep:
        w, c = np.unique(np.asarray(words[i], np.int64), return_counts=True)
        v = c / c.sum() * idf[w]
        s = v.sum()
        # every word has idf 0 (held by every training subimage): a uniform histogram of them
        v = v / s if s > 0 else np.full(len(w), 1.0 / len(w))
        indices.append(w)
        data.append(v)
        indptr.append(indptr[-1] + len(w))
    mat = sp.csr_matrix(
        (
            np.concatenate(data) if data else np.zeros(0),
            np.concatenate(indices) if indices else np.zeros(0, np.int64),
            np.asarray(indptr, np.int64),
        ),
        shape=(len(keep), k),
    )
    return mat, keep


def encode_words(
    bc: BovwConfig, vocab_dir: Path, frames: pd.DataFrame, rows: pd.DataFrame, name: str, tmp: Path
) -> dict[str, Any]:
    """Word histograms of every subimage of ``rows`` into ``tmp``.

    ``words.npz`` (CSR, one row per subimage with a feature) aligned with ``index.parquet`` (the
    proposal rows of those subimages); subimages without a feature are counted, not written.
    The words of a subimage the vocabulary was trained on are read from its entry (the same
    words, extracted once): a map session's encoding then extracts features only of the
    subimages the vocabulary's sample left out.
    """
    import faiss

    vocab = np.load(vocab_dir / "vocab.npy")
    idf = np.load(vocab_dir / "idf.npy")
    index = faiss.IndexFlatL2(vocab.shape[1])
    index.add(vocab)
    words, known = _trained_words(vocab_dir, rows)
    nfeat = sum(len(words[i]) for i in known)
    rest = np.setdiff1d(np.arange(len(rows)), known)
    todo = rows.iloc[rest].reset_index(drop=True)
    for idx, fs in iter_features(bc, todo, frames, f"bovw words {name}") if len(todo) else ():
        for i, f in zip(rest[idx], fs, strict=True):
            if len(f):
                _, w = index.search(np.ascontiguousarray(f, np.float32), 1)
                words[int(i)] = w[:, 0].astype(np.int64)
                nfeat += len(f)
    mat, keep = bow_vectors(words, idf)
    sp.save_npz(tmp / "words.npz", mat, compressed=False)
    write_parquet(tmp / "index.parquet", rows.iloc[keep].reset_index(drop=True))
    return {
        "subimages": len(rows),
        "no_feature_subimages": int(len(rows) - len(keep)),
        "features": int(nfeat),
        "words_from_vocabulary": len(known),
    }


def _trained_words(vocab_dir: Path, rows: pd.DataFrame) -> tuple[list[np.ndarray], np.ndarray]:
    """Each row's words where the vocabulary's sample holds its box, else none; and those rows.

    The sample's words are the ones :func:`encode_words` would compute: the same crop, features
    and nearest word of each, computed once in the vocabulary's entry.
    """
    words: list[np.ndarray] = [np.zeros(0, np.int64)] * len(rows)
    path = vocab_dir / TRAIN_WORDS
    if not len(rows) or not path.is_file():
        return words, np.zeros(0, np.int64)
    trained = read_cached_parquet(path)
    at = pd.MultiIndex.from_frame(trained[BOX_KEY]).get_indexer(
        pd.MultiIndex.from_frame(rows[BOX_KEY])
    )
    known = np.nonzero(at >= 0)[0]
    for i in known:
        words[int(i)] = np.asarray(trained["words"].iloc[at[i]], np.int64)
    return words, known


def combine_word_shards(parts: list[Path], tmp: Path) -> dict[str, Any]:
    """A session's word shards stacked into one ``words.npz`` + ``index.parquet``."""
    mats = [sp.load_npz(p / "words.npz") for p in parts]
    idx = [read_cached_parquet(p / "index.parquet") for p in parts]
    k = mats[0].shape[1] if mats else 0
    mat = sp.vstack(mats, format="csr") if mats else sp.csr_matrix((0, k))
    df = pd.concat(idx, ignore_index=True) if idx else pd.DataFrame()
    sp.save_npz(tmp / "words.npz", mat.tocsr(), compressed=False)
    write_parquet(tmp / "index.parquet", df)
    return {"subimages_with_words": int(mat.shape[0])}


def load_words(entry: Path) -> sp.csr_matrix:
    """A word entry's CSR matrix (aligned with its ``index.parquet``)."""
    return sp.load_npz(entry / "words.npz").tocsr()


def frame_similarity(
    query: sp.csr_matrix, inverted: sp.csc_matrix, order: np.ndarray, starts: np.ndarray
) -> np.ndarray:
    """(n, L) largest L1 score of each query to each database frame, through the inverted index.

    ``inverted`` is the database (rows = subimages, columns = words) in CSC form: column w is
    word w's posting list. For each query only the postings of its own words are visited:
    ``s(q, j) = sum_w min(q_w, D_jw)`` accumulated with ``bincount`` into one database-length
    vector, then the per-frame maximum (``order`` groups the rows by frame, ``starts`` begins
    each frame's group). A frame that shares no word with q scores 0.
    """
    n, m = query.shape[0], inverted.shape[0]
    out = np.zeros((n, len(starts)), np.float64)
    ip, ix, dat = inverted.indptr, inverted.indices, inverted.data
    for i in range(n):
        a, b = query.indptr[i], query.indptr[i + 1]
        w, qv = query.indices[a:b], query.data[a:b]
        s0, lens = ip[w], ip[w + 1] - ip[w]
        tot = int(lens.sum())
        if tot == 0:
            continue
        pos = np.repeat(s0 - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens) + np.arange(tot)
        v = np.minimum(dat[pos], np.repeat(qv, lens))
        s = np.bincount(ix[pos], weights=v, minlength=m)
        out[i] = np.maximum.reduceat(s[order], starts) if len(starts) else 0.0
    return out


def bovw_ranks(
    query: sp.csr_matrix,
    db: sp.csr_matrix,
    db_frame: np.ndarray,
    gt_frame: np.ndarray,
    place: Sequence[np.ndarray] | None = None,
    query_batch: int = 256,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image-level ranks of the ground-truth places under the L1 score (method §6 and 11).

    ``dist(q, F) = 1 - max_{j in F} s(q, j)``; ``d``, ``rank`` and ``L`` as method §6 (ties
    in q's favour). Memory: the inverted index plus a (query_batch x frames) block.

    Returns:
        ``rank`` (n,) int64, ``L`` (n,) int64, ``dist`` (n,) float64 (= ``d``).
    """
    db_frame, gt_frame = np.asarray(db_frame), np.asarray(gt_frame)
    if query.shape[1] != db.shape[1]:
        raise RetrievalError(f"vocabularies disagree: query {query.shape}, database {db.shape}")
    order, frame_ids, starts = frame_layout(db_frame)
    pcols = place_columns(frame_ids, gt_frame, place)
    inverted = db.tocsc()
    n, L = query.shape[0], len(frame_ids)
    rank, Lq, dist = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.float64)
    for b0 in range(0, n, query_batch):
        b1 = min(n, b0 + query_batch)
        fd = 1.0 - frame_similarity(query[b0:b1], inverted, order, starts)
        for j, i in enumerate(range(b0, b1)):
            in_place = np.zeros(L, bool)
            in_place[pcols[i]] = True
            dg = float(fd[j, in_place].min())
            rank[i] = 1 + int(((fd[j] < dg) & ~in_place).sum())
            Lq[i] = L - int(in_place.sum()) + 1
            dist[i] = dg
    return rank, Lq, dist

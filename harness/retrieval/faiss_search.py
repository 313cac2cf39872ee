"""The optional faiss engine (method §6): the same ranks from a top-k search.

Exact for every query whose ground-truth frame is among the top k; otherwise a lower bound,
flagged.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from harness.errors import RetrievalError
from harness.retrieval.layout import Ranks, frame_layout, place_columns

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FaissSearch:
    """The top-k search of :func:`image_ranks_faiss`.

    ``k`` neighbours per query subimage; ``nlist`` > 0: an IVF index of that many lists (trained
    on a sample drawn with ``seed``), ``nprobe`` of them searched; 0: a flat index.
    """

    k: int = 256
    nlist: int = 0
    nprobe: int = 8
    seed: int = 0


def image_ranks_faiss(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    db_frame: np.ndarray,
    gt_frame: np.ndarray,
    place: Sequence[np.ndarray] | None = None,
    search: FaissSearch = FaissSearch(),
) -> Ranks:
    """Approximate ranks from a faiss top-k subimage search.

    ``d`` is computed exactly from the place's own rows. Frames outside the place among the top k
    with a smaller distance are counted; when the k-th distance is still below ``d`` frames
    beyond the top k may be better too, so the rank is a lower bound and ``exact`` is False.
    ``place`` as in :func:`image_ranks`; ``search``: the top k and the index.
    """
    k, nlist, nprobe, seed = search.k, search.nlist, search.nprobe, search.seed
    try:
        import faiss
    except ImportError as err:  # pragma: no cover - faiss is in the dev extra
        raise RetrievalError(
            "the faiss engine needs faiss: pip install 'dbl-harness[faiss]'"
        ) from err
    q = np.ascontiguousarray(query_desc, dtype=np.float32)
    db = np.ascontiguousarray(db_desc, dtype=np.float32)
    d = db.shape[1]
    if nlist > 0:
        index: Any
        quant = faiss.IndexFlatL2(d)
        index = faiss.IndexIVFFlat(quant, d, nlist)
        rs = np.random.default_rng(seed)
        index.train(db[rs.choice(len(db), size=min(len(db), max(nlist * 39, 1000)), replace=False)])
        index.nprobe = nprobe
    else:
        index = faiss.IndexFlatL2(d)
    index.add(db)
    kk = min(k, len(db))
    D, idx = index.search(q, kk)
    order, frame_ids, starts = frame_layout(np.asarray(db_frame))
    L = len(frame_ids)
    pcols = place_columns(frame_ids, np.asarray(gt_frame), place)
    rank = np.empty(len(q), np.int64)
    dist = np.empty(len(q), np.float64)
    exact = np.empty(len(q), bool)
    bounds = np.concatenate([starts, [len(order)]])
    for i in range(len(q)):
        rows = np.concatenate([order[bounds[c] : bounds[c + 1]] for c in pcols[i]])
        dg2 = float(((db[rows].astype(np.float64) - q[i]) ** 2).sum(1).min())
        found = idx[i] >= 0
        fr = np.asarray(db_frame)[idx[i][found]]
        dd = D[i][found]
        members = set(frame_ids[pcols[i]].tolist())
        better = {f for f, v in zip(fr.tolist(), dd, strict=True) if v < dg2 and f not in members}
        rank[i] = 1 + len(better)
        dist[i] = np.sqrt(dg2)
        exact[i] = bool(len(dd) == len(db) or (len(dd) and dd[-1] >= dg2))
    sizes = np.array([len(c) for c in pcols], np.int64)
    return Ranks(rank, L - sizes + 1, dist, exact, sizes)

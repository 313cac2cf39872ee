"""Bench case ``localizers``: the bag-of-visual-words engine next to the autoencoder, same run.

NCLT-sized work (method §11): subimages of 1,232 x 1,616 frames resized to the localizers' inputs
(BoVW 128 x 128 dense RootSIFT, the autoencoder 256 x 256), a vocabulary of k = 1,024 words from
200,000 features, and ranking against databases of 10,000 and 100,000 reference subimages (an
NCLT session of about 6,000 kept frames x 16 subimages is the latter's order). For each engine:
time per subimage (encode) or per query subimage (rank) and the memory its database takes, next
to the autoencoder's exact engine on the same database size.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import cv2
import numpy as np

from .common import emit, peak_rss_mib, timed


def _textured(rng: np.random.Generator, n: int, size: int) -> np.ndarray:
    """``n`` RGB crops with image-like gradients (blurred noise at two scales), uint8."""
    out = np.empty((n, size, size, 3), np.uint8)
    for i in range(n):
        a = cv2.GaussianBlur(rng.uniform(0, 255, (size, size, 3)).astype(np.float32), (0, 0), 3)
        b = cv2.resize(rng.uniform(0, 255, (size // 8, size // 8, 3)).astype(np.float32),
                       (size, size))  # fmt: skip
        out[i] = np.clip(0.5 * a + 0.5 * b, 0, 255).astype(np.uint8)
    return out


def _sparse_db(rng: np.random.Generator, n: int, k: int, words: int) -> Any:
    """``n`` TF-IDF L1 vectors of about ``words`` distinct words each (Zipf-like word use)."""
    from harness.retrieval.bovw import bow_vectors

    p = 1.0 / np.arange(1, k + 1) ** 0.8
    p /= p.sum()
    idf = np.log(1.0 / np.maximum(p * words, 1e-6)).clip(0.1)
    ws = [rng.choice(k, size=words, p=p) for _ in range(n)]
    return bow_vectors(ws, idf)[0]


def case_localizers(quick: bool) -> None:
    import faiss
    import torch

    from harness.descriptors import AutoencoderDescriptor
    from harness.descriptors.autoencoder import ConvAutoencoder
    from harness.descriptors.config import DescriptorConfig
    from harness.retrieval.bovw import bovw_ranks, features
    from harness.retrieval.config import BovwConfig
    from harness.retrieval.engines import image_ranks

    rng = np.random.default_rng(0)
    bc = BovwConfig(features="rootsift", k=1024, input_size=128, step=8, patch=16)
    n = 64 if quick else 256
    crops = _textured(rng, n, 128)
    feats = features(bc, crops)
    runs = [n / t for t in timed(lambda: features(bc, crops), repeat=3)]
    per = statistics.mean(len(f) for f in feats)
    # vocabulary: k-means of k words on 200,000 features (the default max_train_features)
    nf = 50_000 if quick else 200_000
    allf = np.concatenate(feats)
    train = allf[rng.integers(0, len(allf), nf)] + rng.normal(0, 0.02, (nf, allf.shape[1])).astype(
        np.float32
    )
    t0 = time.perf_counter()
    km = faiss.Kmeans(train.shape[1], bc.k, niter=bc.kmeans_iter, seed=0, verbose=False)
    km.train(np.ascontiguousarray(train, np.float32))
    t_vocab = time.perf_counter() - t0
    emit(
        "bovw vocabulary (faiss k-means)",
        [t_vocab],
        "s",
        notes=f"k = {bc.k}, {nf:,} RootSIFT features x 128, {bc.kmeans_iter} iterations; "
        f"{bc.k * 128 * 4 / 1e6:.1f} MB of words",
    )
    index = faiss.IndexFlatL2(128)
    index.add(np.ascontiguousarray(km.centroids, np.float32))

    def encode() -> None:
        for f in features(bc, crops):
            index.search(f, 1)

    enc = [n / t for t in timed(encode, repeat=3)]
    emit(
        "bovw encode 128x128 (dense RootSIFT + word assignment)",
        enc,
        "subimages/s",
        notes=f"{per:.0f} features per subimage; features alone {statistics.median(runs):.0f} "
        f"subimages/s; {1000 / statistics.median(enc):.2f} ms/subimage",
    )
    ae = AutoencoderDescriptor(DescriptorConfig(input_size=256, batch_size=32, device="cpu"))
    ae.model = ConvAutoencoder().eval()
    x = _textured(rng, 64 if quick else 128, 256)
    ae.encode(x[:32])
    ae_rate = [len(x) / t for t in timed(lambda: ae.encode(x), repeat=3)]
    emit(
        "autoencoder encode 256x256 (same run)",
        ae_rate,
        "subimages/s",
        notes=f"{1000 / statistics.median(ae_rate):.2f} ms/subimage; BoVW encode / autoencoder "
        f"encode = {statistics.median(enc) / statistics.median(ae_rate):.2f}x the rate; torch "
        f"threads {torch.get_num_threads()}",
    )
    # distinct words per subimage, as the features above give them
    distinct = [len(np.unique(index.search(f, 1)[1][:, 0])) for f in feats[:32] if len(f)]
    words = int(statistics.median(distinct))
    nq = 64 if quick else 256
    for m in (10_000,) if quick else (10_000, 100_000):
        db = _sparse_db(rng, m, bc.k, words)
        q = _sparse_db(rng, nq, bc.k, words)
        frames = np.repeat(np.arange(m // 16), 16)[:m]
        gt = rng.integers(0, m // 16, nq)
        place = [np.array([g]) for g in gt]
        br = [
            nq / t
            for t in timed(
                lambda q=q, db=db, f=frames, g=gt, pl=place: bovw_ranks(q, db, f, g, pl), repeat=3
            )
        ]
        bytes_inv = db.data.nbytes + db.indices.nbytes + db.indptr.nbytes
        ae_bytes = m * 16384 * 2
        note = (
            f"{m:,} database subimages, {words} distinct words each; inverted index "
            f"{bytes_inv / 1e6:.0f} MB vs the autoencoder's float16 database "
            f"{ae_bytes / 1e9:.2f} GB"
        )
        if m == 10_000:
            dbd = rng.standard_normal((m, 16384)).astype(np.float16)
            qd = rng.standard_normal((nq, 16384)).astype(np.float32)

            def exact(qd=qd, d=dbd, f=frames, g=gt, pl=place) -> None:  # type: ignore[no-untyped-def]
                image_ranks(qd, d, f, g, pl)

            ex = [nq / t for t in timed(exact, repeat=3)]
            note += (
                f"; exact autoencoder engine, same database size: {statistics.median(ex):.0f} "
                f"queries/s (BoVW / exact = {statistics.median(br) / statistics.median(ex):.2f}x)"
            )
            del dbd
        emit(f"bovw rank, {m // 1000}k database subimages", br, "query subimages/s", notes=note)
    emit("localizers case peak memory", [peak_rss_mib()], "MiB", notes="whole case, ru_maxrss")
    table_l(quick)


def table_l(quick: bool) -> None:
    """Table L of ``harness reproduce`` with both localizers on the NCLT-scale workload."""
    import json
    import shutil

    from .common import ROOT, nclt_scale_workload, reproduce_subprocess

    n = 24 if quick else 48
    root = nclt_scale_workload(n)
    out, run, usage, wall = reproduce_subprocess(
        ROOT / "bench" / "nclt_localizers.toml", root, "table-l-"
    )
    md = (out / "tableL.md").read_text()
    t = run["timings_s"]
    shutil.rmtree(out)
    rows = [line for line in md.splitlines() if line.startswith("|")]
    print(
        json.dumps(
            {
                "case": f"Table L, autoencoder + BoVW [{n} frames/session, 1232x1616]",
                "median": wall,
                "unit": "s",
                "runs": [wall],
                "peak_rss_mib": usage.ru_maxrss / 1024,
                "table_l": rows,
                "notes": "stages s: " + ", ".join(f"{k} {float(v):.1f}" for k, v in t.items()),
            }
        ),
        flush=True,
    )

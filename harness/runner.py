"""The pipeline: ingest, pairs, proposals, descriptor training and extraction, ranks, fusion,
labels, AP. Each stage unit is cached under ``<out>/cache/<stage>/<key>/`` by a key of its inputs
and config; a rerun with nothing changed does no work, an interrupted run resumes, and changing
one option reruns only what depends on it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

from . import __version__
from .annotations import change_boxes, load_annotations
from .cache import StageCache, file_fingerprint, stable_hash, write_json, write_parquet, write_text
from .config import FUSION_METHODS, Config
from .crops import iter_crops
from .descriptors import make_descriptor, normalize
from .errors import ConfigError, HarnessError, RetrievalError
from .executors import LocalExecutor
from .fusion import cover_matrix, intersection_closure, loc_from_cover
from .ingest import ingest_session, load_frames
from .ingest.logs import detect_format
from .metrics import average_precision, bootstrap_ap, pr_curve
from .pairs import build_pairs
from .proposals import compute_proposals
from .records import FRAME_SCHEMA
from .retrieval import image_ranks, image_ranks_faiss
from .splits import label as split_label
from .splits import paper_splits, roc_sob

log = logging.getLogger(__name__)

METHOD_LABELS = {
    "rank_fusion": "rank fusion",
    "rank_fusion_le2": "rank fusion (<=2)",
    "rank_fusion_le3": "rank fusion (<=3)",
    "rank_no_fusion": "rank w/o fusion",
    "score_max": "score max",
    "score_sum": "score sum",
}


def _progress(iterable, **kw):
    return tqdm(iterable, mininterval=1.0, dynamic_ncols=True, leave=False, disable=None, **kw)


def file_sha(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def source_fingerprint(session: Any) -> dict:
    """Identity of a session's source: only the files that session reads."""
    src = Path(session.source)
    fmt = detect_format(src) if session.format == "auto" else session.format
    if fmt == "nclt":
        return {
            "images": file_fingerprint(src / "images" / session.name / "lb3" / session.camera),
            "gt": file_fingerprint(src / "ground_truth" / f"groundtruth_{session.name}.csv"),
        }
    return file_fingerprint(src)


@dataclass
class Pipeline:
    """Runs the stages of one config into one output directory."""

    cfg: Config
    out: Path
    rank_import: Path | None = None
    executor: Any = field(default_factory=LocalExecutor)
    timings: dict[str, float] = field(default_factory=dict)
    ran: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.out = Path(self.out).resolve()  # workers of a remote executor may start elsewhere
        self.cache = StageCache(self.out / "cache")

    # ------------------------------------------------------------ helpers
    def _timed(self, name: str, fn: Callable[[], Any]) -> Any:
        t0 = time.perf_counter()
        res = fn()
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        return res

    def _map(self, name: str, units: list[tuple[tuple, Callable[[Path], dict | None]]], gpu: bool = False) -> list[tuple[Path, str]]:
        """Run independent cached units through the executor (in parallel where it can)."""
        t0 = time.perf_counter()
        res = self.executor.map_units(self.cache, name, units, gpu=gpu)
        self.ran[name] = self.ran.get(name, 0) + sum(int(r) for _, r in res)
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        return [(p, p.name) for p, _ in res]

    def _run(self, name: str, key_parts: tuple, build: Callable[[Path], dict | None]) -> tuple[Path, str]:
        path, ran = self.cache.run(name, key_parts, build)
        self.ran[name] = self.ran.get(name, 0) + int(ran)
        return path, path.name

    # ------------------------------------------------------------ stages
    def fixture(self) -> None:
        fx = self.cfg.fixture
        if not fx.generate or (self.cfg.data_root / "fixture.json").exists():
            return
        from .fixture import FixtureSpec, generate

        log.info("fixture: generating into %s", self.cfg.data_root)
        spec = FixtureSpec(seed=fx.seed, frames=fx.frames, width=fx.width, height=fx.height, objects=fx.objects,
                           loop_scale=fx.loop_scale, render_scale=fx.render_scale)
        try:
            self._timed("fixture", lambda: generate(self.cfg.data_root, spec, formats=fx.formats or None))
        except ValueError as err:
            raise ConfigError(f"[fixture] {err}") from None
        generated_ann = self.cfg.data_root / "annotations.csv"
        if not self.cfg.annotations.exists():
            self.cfg.annotations.parent.mkdir(parents=True, exist_ok=True)
            write_text(self.cfg.annotations, generated_ann.read_text())

    def ingest(self) -> dict[str, tuple[Path, str]]:
        ic = self.cfg.ingest
        units = [
            (("ingest", dataclasses.asdict(sc), dataclasses.asdict(ic), source_fingerprint(sc)), lambda tmp, sc=sc: ingest_session(sc, ic, tmp))
            for sc in self.cfg.sessions
        ]
        return dict(zip([sc.name for sc in self.cfg.sessions], self._map("ingest", units), strict=True))

    def frames(self, ingested: dict[str, tuple[Path, str]]) -> tuple[pd.DataFrame, str]:
        keys = [k for _, k in ingested.values()]

        def build(tmp: Path) -> dict:
            df = pd.concat([load_frames(p / "frames.parquet") for p, _ in ingested.values()], ignore_index=True)
            write_parquet(tmp / "frames.parquet", df.sort_values(["session", "camera", "utime"]), schema=FRAME_SCHEMA)
            return {"frames": len(df)}

        path, key = self._run("frames", tuple(keys), build)
        return pd.read_parquet(path / "frames.parquet"), key

    def pairs(self, frames: pd.DataFrame, frames_key: str, ann: pd.DataFrame, ann_key: str) -> tuple[pd.DataFrame, str]:
        pc = self.cfg.pairs
        queries = ann if pc.queries == "annotated" else None

        def build(tmp: Path) -> dict:
            pairs, summary = build_pairs(frames, pc, self.cfg.seasons(), queries)
            write_parquet(tmp / "pairs.parquet", pairs)
            write_json(tmp / "summary.json", summary)
            return summary

        path, key = self._run("pairs", (frames_key, dataclasses.asdict(pc), ann_key if queries is not None else None, self.cfg.seasons()), build)
        return pd.read_parquet(path / "pairs.parquet"), key

    def proposals(self, frames: pd.DataFrame, ingested: dict[str, tuple[Path, str]]) -> dict[str, tuple[pd.DataFrame, str]]:
        pc = self.cfg.proposals
        file_fp = file_fingerprint(Path(pc.file)) if pc.file and Path(pc.file).exists() else pc.file
        out = {}
        for sc in self.cfg.sessions:
            fr = frames[frames["session"] == sc.name]

            def build(tmp: Path, fr: pd.DataFrame = fr, name: str = sc.name) -> dict:
                df = compute_proposals(fr, pc, progress=lambda it, n=name: _progress(it, desc=f"proposals {n}", unit="batch"))
                write_parquet(tmp / "proposals.parquet", df)
                return {"rows": len(df), "per_method": df.groupby("method").size().to_dict()}

            path, key = self._timed("proposals", lambda b=build, s=sc.name: self._run("proposals", (ingested[s][1], dataclasses.asdict(pc), file_fp), b))
            out[sc.name] = (pd.read_parquet(path / "proposals.parquet"), key)
        return out

    def train(self, frames: pd.DataFrame, props: dict[str, tuple[pd.DataFrame, str]]) -> tuple[Path, str]:
        dc = self.cfg.descriptor
        desc = make_descriptor(dc)
        # options that only affect encoding or execution do not change the trained model
        tkey = {k: v for k, v in dataclasses.asdict(dc).items() if k not in ("num_workers", "shard_frames", "encode_batch", "dtype")}
        if not desc.needs_training:
            return self._run("model", (tkey,), lambda tmp: {"trained": False})

        def build(tmp: Path) -> dict:
            rows = pd.concat([p for p, _ in props.values()], ignore_index=True)
            rng = np.random.default_rng(dc.seed)
            n = min(len(rows), dc.max_train_subimages)
            pick = np.sort(rng.choice(len(rows), size=n, replace=False))
            rows = rows.iloc[pick].reset_index(drop=True)
            img = rows.merge(frames[["session", "camera", "utime", "image"]], on=["session", "camera", "utime"], how="left")["image"]
            data = np.lib.format.open_memmap(tmp / "train_crops.npy", mode="w+", dtype=np.uint8, shape=(n, dc.input_size, dc.input_size, 3))
            for idx, crops in _progress(iter_crops(rows, img, dc.input_size, num_workers=dc.num_workers), desc="training crops", unit="batch"):
                data[idx] = crops
            data.flush()
            bar = tqdm(total=dc.epochs * int(np.ceil(n / dc.batch_size)), desc="autoencoder training", unit="step", mininterval=1.0, leave=False, disable=None)
            info = desc.fit(data, tmp, progress=bar.update)  # type: ignore[call-arg]
            bar.close()
            del data
            (tmp / "train_crops.npy").unlink()
            return info

        keys = sorted(k for _, k in props.values())
        return self._timed("train", lambda: self._run("model", (tkey, keys), build))

    def describe(self, frames: pd.DataFrame, props: dict[str, tuple[pd.DataFrame, str]], model: tuple[Path, str]) -> dict[str, tuple[Path, str]]:
        """Descriptors of every proposal row, per session.

        Work is cached in shards of ``shard_frames`` frames (an interrupted extraction resumes at
        the next unfinished shard); a session's shards are then combined into one float16
        ``desc.npy`` aligned with its ``index.parquet``, copying one shard at a time.
        """
        dc = self.cfg.descriptor
        desc = make_descriptor(dc)
        if desc.needs_training:
            desc.load(model[0])
        # execution-only options do not change the descriptors, so they stay out of the keys
        dkey = {k: v for k, v in dataclasses.asdict(dc).items() if k not in ("num_workers", "shard_frames")}
        units, session_shards = [], {}
        for sc in self.cfg.sessions:
            rows, pkey = props[sc.name]
            utimes = np.unique(rows["utime"].to_numpy())
            shards = [utimes[i : i + dc.shard_frames] for i in range(0, len(utimes), max(1, dc.shard_frames))]
            session_shards[sc.name] = (len(units), len(shards))
            for si, ut in enumerate(shards):
                sub = rows[rows["utime"].isin(ut)]
                fr = frames[frames["session"] == sc.name]

                def build_shard(tmp: Path, sub: pd.DataFrame = sub, fr: pd.DataFrame = fr, name: str = f"{sc.name} [{si + 1}/{len(shards)}]") -> dict:
                    return _encode_rows(desc, dc, fr, sub, tmp, name)

                units.append(((pkey, model[1], dkey, int(ut[0]), int(ut[-1]), len(ut)), build_shard))
        done = self._map("descriptor_shards", units, gpu=True)
        out = {}
        for sc in self.cfg.sessions:
            rows, pkey = props[sc.name]
            first, n = session_shards[sc.name]
            shard_dirs = [p for p, _ in done[first : first + n]]

            def combine(tmp: Path, rows: pd.DataFrame = rows, shard_dirs: list[Path] = shard_dirs) -> dict:
                pos = pd.Series(np.arange(len(rows)), index=pd.MultiIndex.from_frame(rows[["method", "utime", "box_id"]]))
                arr = None
                for d in shard_dirs:
                    idx = pd.read_parquet(d / "index.parquet", columns=["method", "utime", "box_id"])
                    v = np.load(d / "desc.npy", mmap_mode="r")
                    if arr is None:
                        arr = np.lib.format.open_memmap(tmp / "desc.npy", mode="w+", dtype=np.dtype(dc.dtype), shape=(len(rows), v.shape[1]))
                    arr[pos.loc[pd.MultiIndex.from_frame(idx)].to_numpy()] = v
                if arr is None:
                    np.save(tmp / "desc.npy", np.zeros((0, 1), dc.dtype))
                else:
                    arr.flush()
                write_parquet(tmp / "index.parquet", rows)
                return {"subimages": len(rows), "shards": len(shard_dirs), "dim": int(arr.shape[1]) if arr is not None else 0}

            path, key = self._run("descriptors", (pkey, model[1], dkey, [d.name for d in shard_dirs]), combine)
            out[sc.name] = (path, key)
        return out

    def ranks(self, frames: pd.DataFrame, pairs: pd.DataFrame, pairs_key: str, described: dict[str, tuple[Path, str]]) -> tuple[pd.DataFrame, str, dict]:
        rc = self.cfg.retrieval
        if self.rank_import is not None:
            from .ranks_import import ranks_from_import, read_import

            def build_imp(tmp: Path) -> dict:
                df, counts = ranks_from_import(read_import(self.rank_import), pairs, str(self.rank_import))
                write_parquet(tmp / "ranks.parquet", df)
                return counts

            path, key = self._run("ranks", ("import", file_fingerprint(self.rank_import), pairs_key), build_imp)
            return pd.read_parquet(path / "ranks.parquet"), key, self.cache.manifest("ranks", key)["info"]
        import torch

        device = "cuda" if rc.engine == "exact" and self.cfg.descriptor.device in ("auto", "cuda") and torch.cuda.is_available() else "cpu"
        dkeys = {s: k for s, (_, k) in described.items()}
        # units: (reference session, chunk of query frames); one engine per method inside each.
        # The chunk size is an execution option: it stays out of the key of what depends on ranks.
        rkey = {k: v for k, v in dataclasses.asdict(rc).items() if k != "query_frames_per_shard"}
        units, unit_ref = [], []
        for ref in [s.name for s in self.cfg.sessions]:
            sub = pairs[pairs["r_session"] == ref].reset_index(drop=True)
            step = max(1, rc.query_frames_per_shard)
            for c0 in range(0, max(len(sub), 1), step):
                chunk = sub.iloc[c0 : c0 + step]

                def build(tmp: Path, chunk: pd.DataFrame = chunk, ref: str = ref) -> dict:
                    df, counts = self._rank_reference(chunk, ref, described, device)
                    write_parquet(tmp / "ranks.parquet", df)
                    return counts

                units.append(((ref, pairs_key, dkeys, rkey, c0, len(chunk)), build))
                unit_ref.append(ref)
        parts, counts_all = [], {}
        for ref, (path, key) in zip(unit_ref, self._map("ranks", units, gpu=True), strict=True):
            parts.append(pd.read_parquet(path / "ranks.parquet"))
            c = counts_all.setdefault(ref, {})
            for k, v in self.cache.manifest("ranks", key)["info"].items():
                c[k] = c.get(k, 0) + v
        df = pd.concat([p for p in parts if len(p)], ignore_index=True) if any(len(p) for p in parts) else pd.DataFrame()
        if len(df):
            df = df.sort_values(["q_session", "q_camera", "q_utime", "r_session", "method", "box_id"]).reset_index(drop=True)
        return df, stable_hash(pairs_key, dkeys, rkey), counts_all

    def _rank_reference(self, sub: pd.DataFrame, ref: str, described: dict[str, tuple[Path, str]], device: str) -> tuple[pd.DataFrame, dict]:
        rc = self.cfg.retrieval
        counts = {"query_subimages": 0, "ranked": 0, "no_rank_reference_frame_has_no_subimage": 0, "query_frames_without_subimages": 0}
        if not len(sub):
            return pd.DataFrame(), counts
        ref_dir = described[ref][0]
        ref_idx = pd.read_parquet(ref_dir / "index.parquet")
        ref_desc = np.load(ref_dir / "desc.npy", mmap_mode="r")
        out = []
        for method in sorted(ref_idx["method"].unique()):
            dbm = np.nonzero((ref_idx["method"] == method).to_numpy())[0]
            db_frame = ref_idx["utime"].to_numpy()[dbm]
            # a memmap view when the method's rows are contiguous (they are: proposals sort by method)
            db = ref_desc[dbm[0] : dbm[-1] + 1] if len(dbm) and dbm[-1] - dbm[0] + 1 == len(dbm) else ref_desc[dbm]
            have = set(np.unique(db_frame).tolist())
            for qs, g in sub.groupby("q_session", sort=True):
                q_idx = pd.read_parquet(described[qs][0] / "index.parquet")
                q_desc = np.load(described[qs][0] / "desc.npy", mmap_mode="r")
                q_idx["row"] = np.arange(len(q_idx))
                qm = q_idx[q_idx["method"] == method].merge(
                    g.rename(columns={"q_session": "session", "q_camera": "camera", "q_utime": "utime"}),
                    on=["session", "camera", "utime"], how="inner")
                counts["query_frames_without_subimages"] += int(len(g) - qm[["session", "camera", "utime"]].drop_duplicates().shape[0])
                if not len(qm):
                    continue
                counts["query_subimages"] += len(qm)
                ok = qm["r_utime"].isin(have).to_numpy()
                counts["no_rank_reference_frame_has_no_subimage"] += int((~ok).sum())
                qm = qm[ok].reset_index(drop=True)
                if not len(qm):
                    continue
                qd = np.asarray(q_desc[np.sort(qm["row"].to_numpy())], np.float32)
                qd = qd[np.argsort(np.argsort(qm["row"].to_numpy(), kind="stable"), kind="stable")]
                if rc.engine == "faiss":
                    res = image_ranks_faiss(qd, np.asarray(db, np.float32), db_frame, qm["r_utime"].to_numpy(), nlist=rc.faiss_nlist, nprobe=rc.faiss_nprobe)
                    rank, L, dist, exact = res.rank, res.L, res.dist, res.exact
                    # recall against the exact engine on a deterministic sample of the queries
                    k = min(len(qd), rc.faiss_check)
                    ex, _, _ = image_ranks(qd[:k], db, db_frame, qm["r_utime"].to_numpy()[:k], chunk_rows=rc.chunk_rows, device=device)
                    counts["faiss_checked"] = counts.get("faiss_checked", 0) + k
                    counts["faiss_rank_equal_exact"] = counts.get("faiss_rank_equal_exact", 0) + int((ex == rank[:k]).sum())
                    counts["faiss_flagged_exact"] = counts.get("faiss_flagged_exact", 0) + int(exact.sum())
                else:
                    rank, L, dist = image_ranks(qd, db, db_frame, qm["r_utime"].to_numpy(), chunk_rows=rc.chunk_rows, query_batch=rc.query_batch, device=device)
                    exact = np.ones(len(rank), bool)
                counts["ranked"] += len(rank)
                out.append(pd.DataFrame({
                    "q_session": qm["session"], "q_camera": qm["camera"], "q_utime": qm["utime"],
                    "r_session": qm["r_session"], "r_camera": qm["r_camera"], "r_utime": qm["r_utime"],
                    "season_pair": qm["season_pair"], "method": method, "box_id": qm["box_id"],
                    "x1": qm["x1"], "y1": qm["y1"], "x2": qm["x2"], "y2": qm["y2"],
                    "rank": rank, "L": np.full(len(rank), L, np.int64), "r": rank / L, "d": dist, "exact": exact,
                }))
        df = pd.concat(out, ignore_index=True) if out else pd.DataFrame()
        if len(df):
            df = df.sort_values(["q_session", "q_camera", "q_utime", "r_session", "method", "box_id"]).reset_index(drop=True)
        return df, counts

    # ------------------------------------------------------------ fusion, labels, AP
    def samples(self, ranks: pd.DataFrame, ranks_key: str, frames: pd.DataFrame, ann: pd.DataFrame, ann_key: str) -> tuple[pd.DataFrame, str]:
        fc, sc = self.cfg.fusion, self.cfg.splits

        def build(tmp: Path) -> dict:
            df, counts = fuse_samples(ranks, frames, ann, fc.seed, fc.max_fused_boxes)
            write_parquet(tmp / "samples.parquet", df)
            return counts

        path, key = self._timed("fusion", lambda: self._run("samples", (ranks_key, ann_key, dataclasses.asdict(fc), dataclasses.asdict(sc)), build))
        return pd.read_parquet(path / "samples.parquet"), key

    def until_pairs(self) -> tuple[dict[str, tuple[Path, str]], pd.DataFrame, str, pd.DataFrame, str, pd.DataFrame, str]:
        """Fixture (if configured), ingest, frames, annotations and pairs.

        Returns:
            (ingested, frames, frames key, annotations, annotations key, pairs, pairs key).
        """
        self.fixture()
        ingested = self.ingest()
        frames, fkey = self._timed("frames", lambda: self.frames(ingested))
        ann = load_annotations(self.cfg.annotations, frames)
        ann_key = file_sha(self.cfg.annotations)
        pairs, pkey = self._timed("pairs", lambda: self.pairs(frames, fkey, ann, ann_key))
        return ingested, frames, fkey, ann, ann_key, pairs, pkey

    def run(self) -> dict:
        """Run every stage; write the reports into ``out``; return the run record."""
        t0 = time.perf_counter()
        ingested, frames, fkey, ann, ann_key, pairs, pkey = self.until_pairs()
        if not len(pairs):
            raise HarnessError("no query frame found a reference frame; check [pairs] and the annotations")
        if self.rank_import is None:
            props = self.proposals(frames, ingested)
            model = self.train(frames, props)
            described = self.describe(frames, props, model)
        else:
            described = {}
        ranks, rkey, rank_counts = self.ranks(frames, pairs, pkey, described)
        if not len(ranks):
            raise RetrievalError("no query subimage got a rank")
        samples, skey = self.samples(ranks, rkey, frames, ann, ann_key)
        t_eval = time.perf_counter()
        table = write_reports(self.cfg, self.out, samples, ranks, frames, ann)
        self.timings["labels_ap_reports"] = time.perf_counter() - t_eval
        record = {
            "config": dataclasses.asdict(self.cfg),
            "versions": _versions(),
            "seed": self.cfg.seed,
            "argv": sys.argv,
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
            "total_s": round(time.perf_counter() - t0, 3),
            "stage_units_run": self.ran,
            "counts": {"frames": len(frames), "annotated_frames": int(ann[["session", "camera", "utime"]].drop_duplicates().shape[0]),
                       "pairs": len(pairs), "ranked_subimages": len(ranks), "samples": len(samples), "rank_counts": rank_counts},
            "keys": {"frames": fkey, "pairs": pkey, "ranks": rkey, "samples": skey},
        }
        write_json(self.out / "run.json", record)
        record["table"] = table
        return record


def _encode_rows(desc: Any, dc: Any, frames: pd.DataFrame, rows: pd.DataFrame, tmp: Path, name: str) -> dict:
    """Crop, encode and L2-normalise ``rows``; write ``desc.npy`` (aligned with ``index.parquet``)."""
    img = rows.merge(frames[["session", "camera", "utime", "image"]], on=["session", "camera", "utime"], how="left")["image"]
    # frames must be contiguous for the loader: order by frame, remember the original row
    order = np.lexsort((rows["box_id"].to_numpy(), rows["method"].to_numpy(), rows["utime"].to_numpy()))
    arr = None
    for idx, crops in _progress(iter_crops(rows.iloc[order], img.iloc[order], dc.input_size, num_workers=dc.num_workers), desc=f"descriptors {name}", unit="batch"):
        v = normalize(desc.encode(crops))
        if arr is None:
            arr = np.lib.format.open_memmap(tmp / "desc.npy", mode="w+", dtype=np.dtype(dc.dtype), shape=(len(rows), v.shape[1]))
        arr[order[idx]] = v.astype(dc.dtype)
    if arr is None:
        np.save(tmp / "desc.npy", np.zeros((0, 1), dc.dtype))
    else:
        arr.flush()
    write_parquet(tmp / "index.parquet", rows)
    return {"subimages": len(rows), "dim": int(arr.shape[1]) if arr is not None else 0}


def _versions() -> dict:
    import cv2
    import rosbags
    import torch

    return {"dbl-harness": __version__, "python": platform.python_version(), "numpy": np.__version__, "pandas": pd.__version__,
            "torch": torch.__version__, "opencv": cv2.__version__, "rosbags": getattr(rosbags, "__version__", "?"), "platform": platform.platform()}


def fuse_samples(ranks: pd.DataFrame, frames: pd.DataFrame, ann: pd.DataFrame, seed: int, max_boxes: int) -> tuple[pd.DataFrame, dict]:
    """Samples of every query image (pair) for all proposal methods together (``proposals = all``)
    and for each method alone, with N, RoC, SoB and the LoC of each fusion method.

    Works on numpy columns of ``ranks`` sorted once by query image (stable, so each image's rows
    keep their order) and builds one table at the end: no per-image pandas objects.
    """
    cb = change_boxes(ann)
    size = dict(zip(frames[["session", "camera", "utime"]].itertuples(index=False, name=None), frames[["width", "height"]].to_numpy(), strict=True))
    counts = {"query_images": 0, "capped_closures": 0}
    methods = sorted(ranks["method"].unique())
    subsets = [("all", methods)] + ([(m, [m]) for m in methods] if len(methods) > 1 else [])
    keys = ["q_session", "q_camera", "q_utime", "r_session"]
    srt = ranks.sort_values(keys, kind="stable")
    kcols = [srt[k].to_numpy() for k in keys]
    method = srt["method"].to_numpy()
    season_pair = srt["season_pair"].to_numpy()
    box_all = srt[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    r_all, d_all = srt["r"].to_numpy(np.float64), srt["d"].to_numpy(np.float64)
    n = len(srt)
    change = np.zeros(n, bool)
    for kc in kcols:
        change[1:] |= kc[1:] != kc[:-1]
    starts = np.concatenate([[0], np.nonzero(change)[0]]) if n else np.zeros(0, np.int64)
    ends = np.append(starts[1:], n)
    cols: dict[str, list] = {c: [] for c in ("q_session", "q_camera", "q_utime", "r_session", "season_pair", "proposals", "x1", "y1", "x2", "y2",
                                             "original", "N", "RoC", "SoB", *(f"loc_{m}" for m in FUSION_METHODS))}
    for a, b in _progress(list(zip(starts, ends, strict=True)), desc="fusion", unit="image"):
        key = (str(kcols[0][a]), str(kcols[1][a]), int(kcols[2][a]), str(kcols[3][a]))
        qkey = key[:3]
        if qkey not in cb:
            continue
        counts["query_images"] += 1
        w, h = size[qkey]
        for name, ms in subsets:
            sel = np.isin(method[a:b], ms)
            if not sel.any():
                continue
            boxes = box_all[a:b][sel]
            r, d = r_all[a:b][sel], d_all[a:b][sel]
            fused, capped = intersection_closure(boxes, max_boxes)
            counts["capped_closures"] += int(capped)
            cover = cover_matrix(fused, boxes)
            img_seed = int(stable_hash(seed, key, name, length=8), 16)
            locs = {m: loc_from_cover(cover, r, d, m, img_seed) for m in FUSION_METHODS if m != "rank_no_fusion"}
            # rank_no_fusion: one sample per original box; merged into the fused row of the same box
            fidx = {tuple(bx): i for i, bx in enumerate(fused)}
            nof = np.full(len(fused), np.nan)
            extra = []
            for k, bx in enumerate(map(tuple, boxes)):
                i = fidx[bx]
                if np.isnan(nof[i]):
                    nof[i] = r[k]
                else:
                    extra.append((bx, r[k]))
            all_boxes = np.vstack([fused, np.array([bx for bx, _ in extra]).reshape(-1, 4)])
            roc, sob = roc_sob(all_boxes, cb[qkey], w, h)
            n_rows, n_x = len(all_boxes), len(extra)
            for c, v in zip(("q_session", "q_camera", "q_utime", "r_session"), key, strict=True):
                cols[c].append(np.full(n_rows, v, dtype=np.int64 if c == "q_utime" else object))
            cols["season_pair"].append(np.full(n_rows, season_pair[a], dtype=object))
            cols["proposals"].append(np.full(n_rows, name, dtype=object))
            for j, c in enumerate(("x1", "y1", "x2", "y2")):
                cols[c].append(all_boxes[:, j])
            cols["original"].append(np.concatenate([~np.isnan(nof), np.ones(n_x, bool)]))
            cols["N"].append(np.concatenate([cover.sum(1), np.ones(n_x, np.int64)]).astype(np.int64))
            cols["RoC"].append(np.asarray(roc, np.float64))
            cols["SoB"].append(np.asarray(sob, np.float64))
            cols["loc_rank_no_fusion"].append(np.concatenate([nof, [v for _, v in extra]]))
            for m, v in locs.items():
                cols[f"loc_{m}"].append(np.concatenate([v, np.full(n_x, np.nan)]))
    if not cols["x1"]:
        return pd.DataFrame(), counts
    df = pd.DataFrame({c: np.concatenate(v) for c, v in cols.items()})
    return df, counts


def _ap_rows(df: pd.DataFrame, split: Any, cfg: Config, season_pair: str, proposals: str) -> list[dict]:
    rows = []
    lab = split_label(df["RoC"].to_numpy(), df["SoB"].to_numpy(), split)
    groups = (df["q_session"] + "|" + df["q_utime"].astype(str) + "|" + df["r_session"]).to_numpy()
    for i, m in enumerate(FUSION_METHODS):
        loc = df[f"loc_{m}"].to_numpy()
        sel = (lab >= 0) & ~np.isnan(loc)
        y, s = lab[sel] == 1, loc[sel]
        ap = average_precision(y, s)
        lo, hi = (bootstrap_ap(y, s, groups[sel], cfg.report.bootstrap, cfg.report.ci, cfg.seed + i) if season_pair == "all" and proposals == "all"
                  else (float("nan"), float("nan")))
        rows.append({"split": split.name, "roc_max": split.roc_max, "proposals": proposals, "season_pair": season_pair, "method": m,
                     "ap": ap, "ci_low": lo, "ci_high": hi, "positives": int(y.sum()), "negatives": int((~y).sum()),
                     "left_out": int(((lab < 0) & ~np.isnan(loc)).sum()), "positive_rate": float(y.mean()) if len(y) else float("nan"),
                     "query_images": len(np.unique(groups[sel]))})
    return rows


def write_reports(cfg: Config, out: Path, samples: pd.DataFrame, ranks: pd.DataFrame, frames: pd.DataFrame, ann: pd.DataFrame) -> pd.DataFrame:
    """Table I, per-split reports, the summary, PR plots and LoC-map figures."""
    splits = paper_splits(cfg.splits)
    summary = []
    curves = []
    for sp in _progress(splits, desc="splits", unit="split"):
        lab = split_label(samples["RoC"].to_numpy(), samples["SoB"].to_numpy(), sp)
        rep = samples.assign(label=lab)
        write_parquet(out / "splits" / f"{sp.name}.parquet", rep)
        for prop, g in samples.groupby("proposals", sort=True):
            summary += _ap_rows(g, sp, cfg, "all", str(prop))
            if prop == "all":
                for pair, gp in g.groupby("season_pair", sort=True):
                    summary += _ap_rows(gp, sp, cfg, str(pair), "all")
        allg = rep[rep["proposals"] == "all"]
        for m in FUSION_METHODS:
            sel = (allg["label"] >= 0) & allg[f"loc_{m}"].notna()
            if (allg.loc[sel, "label"] == 1).any():
                thr, p, r = pr_curve(allg.loc[sel, "label"].to_numpy() == 1, allg.loc[sel, f"loc_{m}"].to_numpy())
                curves.append(pd.DataFrame({"split": sp.name, "method": m, "threshold": thr, "precision": p, "recall": r}))
    summ = pd.DataFrame(summary)
    write_parquet(out / "splits" / "summary.parquet", summ)
    if curves:
        write_parquet(out / "splits" / "pr_curves.parquet", pd.concat(curves, ignore_index=True))
    main = summ[(summ["proposals"] == "all") & (summ["season_pair"] == "all")]
    table = main.pivot(index="method", columns="roc_max", values="ap").reindex(list(FUSION_METHODS))
    write_text(out / "table1.csv", table1_csv(table))
    write_text(out / "table1.md", table1_markdown(table, main))
    if cfg.report.plots:
        from .plots import locmap_figures, pr_plots

        if curves:
            pr_plots(pd.concat(curves, ignore_index=True), out / "plots")
        locmap_figures(samples, frames, ann, out / "locmaps", cfg.report.locmap_examples)
    return table


def table1_csv(table: pd.DataFrame) -> str:
    cols = list(table.columns)
    lines = ["method," + ",".join(f"{c:.2f}" for c in cols)]
    for m, row in table.iterrows():
        lines.append(m + "," + ",".join("nan" if np.isnan(v) else f"{v:.2f}" for v in row.to_numpy()))
    return "\n".join(lines) + "\n"


def table1_markdown(table: pd.DataFrame, main: pd.DataFrame) -> str:
    cols = list(table.columns)
    head = "| AP | " + " | ".join(f"{c:.2f}" for c in cols) + " |\n|---|" + "---|" * len(cols) + "\n"
    body = "".join(
        f"| {METHOD_LABELS[m]} | " + " | ".join("NaN" if np.isnan(v) else f"{v:.2f}" for v in row.to_numpy()) + " |\n"
        for m, row in table.iterrows()
    )
    counts = main.drop_duplicates("roc_max").set_index("roc_max")
    rk = main[main["method"] == "rank_fusion"].set_index("roc_max")
    foot = "\nColumns: RoC-max of the negative range. Positives / negatives per column (fused samples): " + ", ".join(
        f"{c:.2f}: {int(rk.loc[c, 'positives'])}/{int(rk.loc[c, 'negatives'])}" for c in cols if c in rk.index) + ".\n"
    del counts
    return head + body + foot


def reproduce(cfg: Config, out: Path, rank_import: Path | None = None, executor: Any = None) -> dict:
    """Run the whole pipeline for ``cfg`` into ``out`` (``executor``: local by default)."""
    return Pipeline(cfg, Path(out), rank_import=rank_import, executor=executor or LocalExecutor()).run()


def load_run(out: Path) -> dict:
    return json.loads((Path(out) / "run.json").read_text())

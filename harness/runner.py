"""The pipeline: ingest, pairs, proposals, descriptor training and extraction, ranks, fusion,
labels, AP. Each stage unit is cached under ``<out>/cache/<stage>/<key>/`` by a key of its inputs
and config; a rerun with nothing changed does no work, an interrupted run resumes, and changing
one option reruns only what depends on it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import platform
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

from . import __version__
from .annotations import load_annotations
from .cache import (
    StageCache,
    file_fingerprint,
    open_memmap_reserved,
    read_cached_parquet,
    stable_hash,
    write_json,
    write_parquet,
    write_text,
)
from .config import Config
from .crops import iter_crops
from .descriptors import make_descriptor, normalize
from .errors import ConfigError, HarnessError, RetrievalError
from .executors import LocalExecutor
from .fusion import fuse_samples, ordered_methods
from .imagestore import local_uri, portable_uri
from .ingest import ingest_session, load_frames
from .ingest.logs import detect_format
from .outdirs import claim_dir, run_lock
from .pairs import build_pairs, ground_truth_places, thin_by_stride
from .proposals import compute_proposals
from .records import FRAME_SCHEMA
from .reports import METHOD_LABELS, write_reports  # noqa: F401 - METHOD_LABELS re-exported for callers
from .retrieval import image_ranks, image_ranks_faiss

log = logging.getLogger(__name__)

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
        # never write into a directory the harness did not create; resolved: remote workers may start elsewhere
        self.out = claim_dir(Path(self.out), "run")
        self.cache = StageCache(self.out / "cache")
        self._lock_depth = 0
        self._lock_cm: Any = None
        self.used: dict[str, set[str]] = {}  # cache entries this pipeline read or wrote: what `harness gc` keeps

    def __getstate__(self) -> dict[str, Any]:
        """Stage units (closures over the pipeline) travel to remote workers; the lock stays here."""
        state = self.__dict__.copy()
        state["_lock_cm"], state["_lock_depth"] = None, 0
        return state

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the run lock of ``out`` (re-entrant within this pipeline); see :func:`harness.outdirs.run_lock`."""
        if self._lock_depth == 0:
            self._lock_cm = run_lock(self.out)
            self._lock_cm.__enter__()
        self._lock_depth += 1
        try:
            yield
        finally:
            self._lock_depth -= 1
            if self._lock_depth == 0:
                cm, self._lock_cm = self._lock_cm, None
                cm.__exit__(None, None, None)

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
        self.used.setdefault(name, set()).update(Path(p).name for p, _ in res)
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        return [(p, p.name) for p, _ in res]

    def _run(self, name: str, key_parts: tuple, build: Callable[[Path], dict | None]) -> tuple[Path, str]:
        path, ran = self.cache.run(name, key_parts, build)
        self.ran[name] = self.ran.get(name, 0) + int(ran)
        self.used.setdefault(name, set()).add(path.name)
        return path, path.name

    # ------------------------------------------------------------ stages
    def fixture(self) -> None:
        """Generate the fixture into ``data_root`` when configured and absent.

        An existing fixture is reused as it is. A ``data_root`` that exists and holds anything
        else is never touched: that is someone's data, and the error says so.
        """
        fx = self.cfg.fixture
        root = self.cfg.data_root
        if not fx.generate or (root / "fixture.json").exists():
            return
        if root.exists() and (not root.is_dir() or any(root.iterdir())):
            raise ConfigError(
                f"{root}: [fixture] generate = true, but data_root exists and holds no generated fixture "
                "(no fixture.json); the harness never writes into it. Set generate = false for real data, "
                "or point data_root (--data-root) at a new directory"
            )
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
            df["image"] = [portable_uri(u, self.out, self.cfg.data_root) for u in df["image"]]
            write_parquet(tmp / "frames.parquet", df.sort_values(["session", "camera", "utime"]), schema=FRAME_SCHEMA)
            return {"frames": len(df)}

        path, key = self._run("frames", tuple(keys), build)
        df = read_cached_parquet(path / "frames.parquet")
        df["image"] = [local_uri(u, self.out, self.cfg.data_root) for u in df["image"]]
        return df, key

    def pairs(self, frames: pd.DataFrame, frames_key: str, ann: pd.DataFrame, ann_key: str) -> tuple[pd.DataFrame, str]:
        pc = self.cfg.pairs
        queries = ann if pc.queries == "annotated" else None

        def build(tmp: Path) -> dict:
            pairs, summary = build_pairs(frames, pc, self.cfg.seasons(), queries)
            write_parquet(tmp / "pairs.parquet", pairs)
            write_json(tmp / "summary.json", summary)
            return summary

        path, key = self._run("pairs", (frames_key, dataclasses.asdict(pc), ann_key if queries is not None else None, self.cfg.seasons()), build)
        return read_cached_parquet(path / "pairs.parquet"), key

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
            out[sc.name] = (read_cached_parquet(path / "proposals.parquet"), key)
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
            data = open_memmap_reserved(tmp / "train_crops.npy", np.uint8, (n, dc.input_size, dc.input_size, 3))
            for idx, crops in _progress(iter_crops(rows, img, dc.input_size, num_workers=dc.num_workers), desc="training crops", unit="batch"):
                data[idx] = crops
            data.flush()
            total = int(np.ceil(dc.train_samples / dc.batch_size)) if dc.train_samples > 0 else dc.epochs * int(np.ceil(n / dc.batch_size))
            bar = tqdm(total=total, desc="autoencoder training", unit="step", mininterval=1.0, leave=False, disable=None)
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
                    idx = read_cached_parquet(d / "index.parquet", columns=["method", "utime", "box_id"])
                    v = np.load(d / "desc.npy", mmap_mode="r")
                    if arr is None:
                        arr = open_memmap_reserved(tmp / "desc.npy", dc.dtype, (len(rows), v.shape[1]))
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
                df, counts = ranks_from_import(read_import(self.rank_import), pairs, str(self.rank_import), frames,
                                               rc.gt_radius_m, self.cfg.pairs.max_yaw_diff_deg)
                write_parquet(tmp / "ranks.parquet", df)
                return counts

            path, key = self._run("ranks", ("import", file_fingerprint(self.rank_import), pairs_key, rc.gt_radius_m), build_imp)
            return read_cached_parquet(path / "ranks.parquet"), key, self.cache.manifest("ranks", key)["info"]
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
                    df, counts = self._rank_reference(chunk, ref, described, device, frames)
                    write_parquet(tmp / "ranks.parquet", df)
                    return counts

                units.append(((ref, pairs_key, dkeys, rkey, c0, len(chunk)), build))
                unit_ref.append(ref)
        parts, counts_all = [], {}
        for ref, (path, key) in zip(unit_ref, self._map("ranks", units, gpu=True), strict=True):
            parts.append(read_cached_parquet(path / "ranks.parquet"))
            c = counts_all.setdefault(ref, {})
            for k, v in self.cache.manifest("ranks", key)["info"].items():
                c[k] = c.get(k, 0) + v
        df = pd.concat([p for p in parts if len(p)], ignore_index=True) if any(len(p) for p in parts) else pd.DataFrame()
        if len(df):
            df = df.sort_values(["q_session", "q_camera", "q_utime", "r_session", "method", "box_id"]).reset_index(drop=True)
        return df, stable_hash(pairs_key, dkeys, rkey), counts_all

    def _rank_reference(self, sub: pd.DataFrame, ref: str, described: dict[str, tuple[Path, str]], device: str,
                        frames: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
        rc = self.cfg.retrieval
        counts = {"query_subimages": 0, "ranked": 0, "no_rank_reference_frame_has_no_subimage": 0, "query_frames_without_subimages": 0}
        if not len(sub):
            return pd.DataFrame(), counts
        ref_frames = frames[frames["session"] == ref]
        places = {}
        kept: set[int] | None = None  # reference frames in the database ([retrieval] db_stride_m)
        for cam, g in sub.groupby("r_camera", sort=True):
            fr = ref_frames[ref_frames["camera"] == cam]
            places[cam] = ground_truth_places(fr, g["r_utime"].to_numpy(), rc.gt_radius_m, self.cfg.pairs.max_yaw_diff_deg)
        if rc.db_stride_m > 0:
            kept = set()
            for _, fr in ref_frames.groupby("camera", sort=True):
                fr = fr.sort_values("utime")
                kept.update(int(u) for u in fr["utime"].to_numpy()[thin_by_stride(fr[["x", "y"]].to_numpy(), rc.db_stride_m)])
            counts["no_rank_place_not_in_database"] = 0
        ref_dir = described[ref][0]
        ref_idx = read_cached_parquet(ref_dir / "index.parquet")
        ref_desc = np.load(ref_dir / "desc.npy", mmap_mode="r")
        out = []
        for method in sorted(ref_idx["method"].unique()):
            in_db = (ref_idx["method"] == method).to_numpy().copy()
            if kept is not None:
                in_db &= ref_idx["utime"].isin(kept).to_numpy()
            dbm = np.nonzero(in_db)[0]
            db_frame = ref_idx["utime"].to_numpy()[dbm]
            # a memmap view when the method's rows are contiguous (they are: proposals sort by method)
            db = ref_desc[dbm[0] : dbm[-1] + 1] if len(dbm) and dbm[-1] - dbm[0] + 1 == len(dbm) else ref_desc[dbm]
            have = set(np.unique(db_frame).tolist())
            for qs, g in sub.groupby("q_session", sort=True):
                q_idx = read_cached_parquet(described[qs][0] / "index.parquet")
                q_desc = np.load(described[qs][0] / "desc.npy", mmap_mode="r")
                q_idx["row"] = np.arange(len(q_idx))
                qm = q_idx[q_idx["method"] == method].merge(
                    g.rename(columns={"q_session": "session", "q_camera": "camera", "q_utime": "utime"}),
                    on=["session", "camera", "utime"], how="inner")
                counts["query_frames_without_subimages"] += int(len(g) - qm[["session", "camera", "utime"]].drop_duplicates().shape[0])
                if not len(qm):
                    continue
                counts["query_subimages"] += len(qm)
                if kept is None:
                    ok = qm["r_utime"].isin(have).to_numpy()
                    counts["no_rank_reference_frame_has_no_subimage"] += int((~ok).sum())
                else:  # a thinned database: the place must keep a frame; it stands in for G
                    ok = np.array([bool(have.intersection(places[c][int(u)].tolist())) for c, u in zip(qm["r_camera"], qm["r_utime"], strict=True)],
                                  bool) if len(qm) else np.zeros(0, bool)
                    counts["no_rank_place_not_in_database"] += int((~ok).sum())
                qm = qm[ok].reset_index(drop=True)
                if not len(qm):
                    continue
                qd = np.asarray(q_desc[np.sort(qm["row"].to_numpy())], np.float32)
                qd = qd[np.argsort(np.argsort(qm["row"].to_numpy(), kind="stable"), kind="stable")]
                gt = qm["r_utime"].to_numpy()
                place = [places[c][int(u)] for c, u in zip(qm["r_camera"], gt, strict=True)]
                if kept is not None:  # G itself may be thinned away: the place's frames in the database stand for it
                    place = [p[np.isin(p, db_frame)] for p in place]
                    gt = np.array([g if g in set(p.tolist()) else p[np.argmin(np.abs(p - g))] for g, p in zip(gt, place, strict=True)], np.int64)
                if rc.engine == "faiss":
                    res = image_ranks_faiss(qd, np.asarray(db, np.float32), db_frame, gt, place, nlist=rc.faiss_nlist, nprobe=rc.faiss_nprobe)
                    rank, L, dist, exact = res.rank, res.L, res.dist, res.exact
                    # recall against the exact engine on a deterministic sample of the queries
                    k = min(len(qd), rc.faiss_check)
                    ex, _, _ = image_ranks(qd[:k], db, db_frame, gt[:k], place[:k], chunk_rows=rc.chunk_rows, device=device)
                    counts["faiss_checked"] = counts.get("faiss_checked", 0) + k
                    counts["faiss_rank_equal_exact"] = counts.get("faiss_rank_equal_exact", 0) + int((ex == rank[:k]).sum())
                    counts["faiss_flagged_exact"] = counts.get("faiss_flagged_exact", 0) + int(exact.sum())
                else:
                    rank, L, dist = image_ranks(qd, db, db_frame, gt, place, chunk_rows=rc.chunk_rows, query_batch=rc.query_batch, device=device)
                    exact = np.ones(len(rank), bool)
                frame_set = np.unique(db_frame)
                place_size = np.array([int(np.isin(p, frame_set).sum()) for p in place], np.int64)
                counts["ranked"] += len(rank)
                out.append(pd.DataFrame({
                    "q_session": qm["session"], "q_camera": qm["camera"], "q_utime": qm["utime"],
                    "r_session": qm["r_session"], "r_camera": qm["r_camera"], "r_utime": qm["r_utime"],
                    "season_pair": qm["season_pair"], "method": method, "box_id": qm["box_id"],
                    "x1": qm["x1"], "y1": qm["y1"], "x2": qm["x2"], "y2": qm["y2"],
                    "rank": rank, "L": L, "r": rank / L, "r_desc": (L + 1 - rank) / L, "d": dist, "exact": exact,
                    "place_size": place_size,
                }))
        df = pd.concat(out, ignore_index=True) if out else pd.DataFrame()
        if len(df):
            df = df.sort_values(["q_session", "q_camera", "q_utime", "r_session", "method", "box_id"]).reset_index(drop=True)
        return df, counts

    # ------------------------------------------------------------ fusion, labels, AP
    def samples(self, ranks: pd.DataFrame, ranks_key: str, frames: pd.DataFrame, ann: pd.DataFrame, ann_key: str) -> tuple[pd.DataFrame, str]:
        fc, sc = self.cfg.fusion, self.cfg.splits

        def build(tmp: Path) -> dict:
            df, counts = fuse_samples(ranks, frames, ann, fc.seed, fc.max_fused_boxes, methods=ordered_methods(fc.methods),
                                      progress=lambda it: _progress(it, desc="fusion", unit="image"))
            write_parquet(tmp / "samples.parquet", df)
            return counts

        path, key = self._timed("fusion", lambda: self._run("samples", (ranks_key, ann_key, dataclasses.asdict(fc), dataclasses.asdict(sc)), build))
        return read_cached_parquet(path / "samples.parquet"), key

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
        with self.locked():
            return self._run_all()

    def _run_all(self) -> dict:
        t0 = time.perf_counter()
        ingested, frames, fkey, ann, ann_key, pairs, pkey = self.until_pairs()
        if not (ann["status"] == "change").any():
            raise HarnessError(
                f"{self.cfg.annotations}: no frame is annotated 'change', so no split has a positive and every AP "
                "would be NaN; annotate at least one change box"
            )
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
        reports = write_reports(self.cfg, self.out, samples, ranks, frames, ann,
                                progress=lambda it: _progress(it, desc="splits", unit="split"))
        self.timings["labels_ap_reports"] = time.perf_counter() - t_eval
        record = {
            "config": dataclasses.asdict(self.cfg),
            "versions": _versions(),
            "seed": self.cfg.seed,
            "argv": sys.argv,
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
            "total_s": round(time.perf_counter() - t0, 3),
            "stage_units_run": self.ran,
            "executor": self.executor.describe(),
            "counts": {"frames": len(frames), "annotated_frames": int(ann[["session", "camera", "utime"]].drop_duplicates().shape[0]),
                       "pairs": len(pairs), "ranked_subimages": len(ranks), "samples": len(samples), "rank_counts": rank_counts},
            "keys": {"frames": fkey, "pairs": pkey, "ranks": rkey, "samples": skey},
            "localization": reports.localization.to_dict(orient="records"),
            "warnings": reports.warnings,
            "ingest": {name: _ingest_summary(path / "ingest_report.json") for name, (path, _) in ingested.items()},
            "cache_entries": {stage: sorted(keys) for stage, keys in sorted(self.used.items())},
        }
        write_json(self.out / "run.json", record)
        if self.cfg.report.html:
            from .report_html import write_html_report

            t_html = time.perf_counter()
            record["report_html"] = str(write_html_report(self.out))
            self.timings["report_html"] = time.perf_counter() - t_html
        record["table"] = reports.tables["I"]
        record["reports"] = reports
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
            arr = open_memmap_reserved(tmp / "desc.npy", dc.dtype, (len(rows), v.shape[1]))
        arr[order[idx]] = v.astype(dc.dtype)
    if arr is None:
        np.save(tmp / "desc.npy", np.zeros((0, 1), dc.dtype))
    else:
        arr.flush()
    write_parquet(tmp / "index.parquet", rows)
    return {"subimages": len(rows), "dim": int(arr.shape[1]) if arr is not None else 0}


def _ingest_summary(path: Path) -> dict:
    """What run.json keeps of a session's ingest report: frames written, drops, pose frames."""
    rep = json.loads(path.read_text())
    return {k: rep[k] for k in ("format", "frames_written", "dropped", "pose_frames", "salvaged") if k in rep}


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    import cv2
    import torch

    def ver(dist: str) -> str:
        try:
            return version(dist)
        except PackageNotFoundError:
            return "?"

    return {"dbl-harness": __version__, "python": platform.python_version(), "numpy": np.__version__, "pandas": pd.__version__,
            "torch": torch.__version__, "opencv": cv2.__version__, "rosbags": ver("rosbags"), "mcap": ver("mcap"), "platform": platform.platform()}


def reproduce(cfg: Config, out: Path, rank_import: Path | None = None, executor: Any = None) -> dict:
    """Run the whole pipeline for ``cfg`` into ``out`` (``executor``: local by default)."""
    return Pipeline(cfg, Path(out), rank_import=rank_import, executor=executor or LocalExecutor()).run()


def load_run(out: Path) -> dict:
    return json.loads((Path(out) / "run.json").read_text())

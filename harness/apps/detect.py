"""``harness detect``: the maintenance-free change detector on a robot's new session (method §13).

Given a map (reference) session and one or more new (query) sessions of a config, every query
frame (thinned by ``[pairs] stride_m``) is paired with the map by pose (method §4), its
subimages are ranked by the config's localizer(s) (method §6 and 11), and the ranks are
fused (method §7, ``--fusion``, default ``rank_fusion``; across localizers when there
are several) into:

- change boxes: the fused qBBs in descending LoC after greedy non-maximum suppression at IoU
  ``[detect] nms_iou`` (OpenCV's ``dnn.NMSBoxes``), at most ``max_boxes`` per frame;
- the frame's change score: the largest LoC of its samples;
- the pixel-wise LoC map of the frames shown (float16 arrays and colour overlays).

Annotations are optional; where some query frames are annotated, the detections are scored
(Table D) with pycocotools: box AP at IoU 0.5 with VOC all-point interpolation (the metric of "The
Change You Want to See", WACV 2023) and COCO AP@[.5:.95], beside a floor (random scores on the
same fused qBBs, through the same NMS). Work is cached per chunk of query frames (an interrupted
run resumes at the next chunk) and mapped through the run's executor (local or Ray).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from harness import kernels
from harness.apps.detect_outputs import DetectResult, write_outputs
from harness.config.assemble import detect_run_config
from harness.config.plugins import plugin_record
from harness.config.schema import Config
from harness.detect import keys as detect_keys
from harness.detect.chunk import detect_chunk
from harness.detect.config import DetectConfig
from harness.detect.null import NullScores, null_choice, null_pairs, null_record, run_moves
from harness.errors import ConfigError, HarnessError
from harness.imagestore import ImageRef
from harness.ingest.names import session_names
from harness.localizers.config import LocalizerConfig
from harness.localizers.kinds import paired_kinds
from harness.pairs import keys as pair_keys
from harness.pairs.modes import kind_of
from harness.pipeline.across import across_localizers, localizer_fusion
from harness.pipeline.chain import Pipeline, pairs_by_retrieval, until_annotations, until_pairs
from harness.pipeline.localizer_stages import Measured, localizer_ranks
from harness.pipeline.stages import frame_proposals, session_proposals
from harness.records import FRAME_KEY, QUERY_KEY
from harness.reports.detect_run import DetectRun
from harness.reports.rerun import check_rerun_target, write_rerun
from harness.runtime.cache import (
    read_cached_parquet,
    write_json,
    write_text,
)
from harness.runtime.executors import LocalExecutor
from harness.runtime.stage import Table

log = logging.getLogger(__name__)


def check_detect_args(
    cfg: Config, map_session: str, query_sessions: list[str], rerun: Path | None
) -> None:
    """Check what :func:`run_detect` is handed beside its config: the sessions, the recording.

    ``cfg.detect`` itself was checked at load.

    Raises:
        ConfigError: an unknown or repeated session, the map among the queries.
    """
    names = [s.name for s in cfg.sessions]
    for s in [map_session, *query_sessions]:
        if s not in names:
            raise ConfigError(f"detect: session {s!r} is not in the config; sessions: {names}")
    if map_session in query_sessions or len(set(query_sessions)) != len(query_sessions):
        raise ConfigError(
            f"detect: --map {map_session} and --query {query_sessions}: each session once, the "
            "map not among the queries"
        )
    if rerun is not None:
        check_rerun_target(Path(rerun))  # before any work: the SDK is there, the path is ours


def _measure(
    p: Any, map_session: str, query_sessions: list[str], local: LocalizerConfig | None
) -> tuple[Any, Any, Any, list, Callable[[pd.DataFrame], Table] | None]:
    """Frames, annotations, pairs, each localizer's ranks and fusion, and how to propose map frames.

    Pairs by pose, or by retrieval where the config says so (method §13.2). ``local``: the local
    localizer that ranks every pair's subimages instead of the config's (method §13.3). Where
    every localizer ranks inside the paired frame, no map frame is proposed here (none is read);
    the last item proposes the map frames it is handed (the no-change null's queries); None where
    pairs by retrieval leave no paired-frame localizer.
    """
    if kind_of(p.cfg.pairs.by) == "retrieval":  # sessions without poses (method §13.2)
        ingested, frames, ann = until_annotations(p)
        pairs, m = pairs_by_retrieval(
            p, ingested, frames, ann, False, (map_session, tuple(query_sessions))
        )
        if local is None:
            return frames, ann, pairs, [m], None
    else:
        ingested, frames, ann, pairs = detect_pairs(p, map_session, query_sessions)
    locs = (local,) if local is not None else tuple(p.localizer_list)
    paired = all(loc.kind in paired_kinds() for loc in locs)
    props = session_proposals(p, frames, pairs, ingested, references=not paired)
    measured = []
    for loc in locs:
        ranks = localizer_ranks(p, loc, frames, pairs, props)
        fusion, notes = localizer_fusion(p, loc, ranks, len(pairs.df))
        measured.append(Measured(loc, ranks, fusion, notes))
    return frames, ann, pairs, measured, partial(frame_proposals, p, map_session, ingested)


def _keys_of(keys: pd.DataFrame) -> frozenset[tuple[str, str, int]]:
    """The frame keys (session, camera, utime) of the rows of ``keys``."""
    return frozenset((str(a), str(b), int(c)) for a, b, c in keys.itertuples(index=False))


def _chunk_units(
    ranks: Any,
    frames: pd.DataFrame,
    opt: DetectConfig,
    dcfg: Config,
    null: bool = False,
    annotated: frozenset[tuple[str, str, int]] = frozenset(),
) -> list[tuple[tuple[Any, ...], Any]]:
    """(cache key, build) of each chunk of ``opt.chunk_frames`` query frames.

    The build is :func:`detect_chunk` on the chunk's ranks; ``null``: the no-change null's;
    ``annotated``: the annotated query frames, the only ones whose plain difference Table D reads.
    """
    chunk_units: list[tuple[tuple[Any, ...], Any]] = []
    qframes = ranks.df[QUERY_KEY].drop_duplicates().sort_values(QUERY_KEY).reset_index(drop=True)
    for c0 in range(0, len(qframes), opt.chunk_frames):
        part = qframes.iloc[c0 : c0 + opt.chunk_frames]
        mask = pd.MultiIndex.from_frame(ranks.df[QUERY_KEY]).isin(pd.MultiIndex.from_frame(part))
        chunk = ranks.df[mask].reset_index(drop=True)
        segments = dcfg.proposals.segments
        plain = frozenset() if null else _keys_of(part) & annotated
        build = partial(
            detect_chunk, chunk, frames, opt, dcfg.fusion, dcfg.proposals, plain_for=plain
        )
        record = opt.record(dcfg.fusion.seed, segments, dcfg.proposals.selective)
        key = detect_keys.detect_chunk(ranks.key, record, c0, len(part), dcfg.fusion, opt.fusion)
        key = (*key, "null") if null else (*key, "plain", sorted(plain))
        chunk_units.append((key, build))
    return chunk_units


def run_detect(
    cfg: Config,
    map_session: str,
    query_sessions: list[str],
    out: Path,
    executor: Any = None,
    rerun: Path | None = None,
) -> DetectResult:
    """The detector on ``query_sessions`` against ``map_session`` into ``out`` (method §13).

    The one way into the detector: ``cfg`` as :func:`harness.config.assemble.load_config` gives it
    (``harness detect`` adds its flags there), checked at load; its ``[detect]`` is the detector.
    With ``rerun``, also a recording for the Rerun viewer there (:mod:`harness.reports.rerun`).

    Raises:
        ConfigError: an unknown or repeated session, the map among the queries, an unknown method.
    """
    opt = cfg.detect
    alarm = opt.alarm
    check_detect_args(cfg, map_session, query_sessions, rerun)
    dcfg = detect_run_config(cfg, map_session, query_sessions, opt)
    t0 = time.perf_counter()
    p = Pipeline(
        dcfg,
        Path(out),
        executor=executor or LocalExecutor(),
        annotations_optional=True,
        train_sessions=(map_session,),  # the model sees the map alone, never the new session
    )
    with p.locked():
        frames, ann, pairs, measured, propose = _measure(
            p, map_session, query_sessions, opt.local_localizer()
        )
        ranks = measured[0].ranks if len(measured) == 1 else across_localizers(measured)
        names_l = [m.loc.name for m in measured]
        annotated = _keys_of(ann.df[FRAME_KEY])
        chunk_units = _chunk_units(ranks, frames.df, opt, dcfg, annotated=annotated)
        entries = p.units("detect", chunk_units)
        dets = pd.concat(
            [read_cached_parquet(e.path / "boxes.parquet") for e in entries], ignore_index=True
        )
        fr = pd.concat(
            [read_cached_parquet(e.path / "frames.parquet") for e in entries], ignore_index=True
        )
        al, aligned = _alignment(p.out, measured, frames.df, dcfg.sessions)
        chunks = partial(_chunk_units, opt=opt, dcfg=dcfg, null=True)
        null = null_scores(p, opt, measured, frames, propose, map_session, chunks, entries)
        run = DetectRun(
            p, dcfg, opt, map_session, query_sessions, names_l, frames.df, pairs.df, ann.df,
            entries, alarm, al, null,
        )  # fmt: skip
        result = write_outputs(run, dets, fr)
        record = result.record
        record["cache_entries"] = {"detect": [e.path.name for e in entries]}
        if null is not None:
            record["cache_entries"]["detect-null"] = list(null.entries)
        record["thin_boxes_dropped"] = _thin_boxes(p, entries)
        record.update(aligned)
        record["kernels"] = kernels.report()
        if plugin_record():
            record["plugins"] = plugin_record()
        if rerun is not None:
            record["rerun"] = write_rerun(
                Path(rerun), p.out, frames.df, map_session, fr, dets, entries, record["options"]
            )
        if p.pairing:
            record["pairing"] = p.pairing
        record["total_s"] = round(time.perf_counter() - t0, 3)
        record["ms_per_query_frame"] = round(1000 * record["total_s"] / max(len(fr), 1), 2)
        write_json(p.out / "detect.json", record)
    return result


def null_scores(
    p: Any,
    opt: DetectConfig,
    measured: list[Any],
    frames: Table,
    propose: Callable[[pd.DataFrame], Table] | None,
    map_session: str,
    chunks: Callable[[Any, pd.DataFrame], list[tuple[tuple[Any, ...], Any]]],
    run_entries: list[Any] | None = None,
) -> NullScores | None:
    """The null pairs scored by the run's detector (None: calibrated within the run).

    ``run_entries``: the run's own detect chunks, whose registrations the perturbed copies'
    moves are drawn from (``[detect.null] moves = "run"``).

    ``propose`` gives the proposals of the map frames it is handed (the null's query frames: the
    run proposed no other map frame); None where the run has no proposals (pairs by retrieval
    without a paired-frame localizer).

    ``chunks`` (ranks, frames) gives the detect chunks' units, as for the query frames. Where the
    config asks for the null but the run's localizer cannot score a pair alone (the paper's
    descriptor localizers rank among the whole map), a WARNING says so and the run is
    calibrated within itself.
    """
    if opt.calibration != "null":
        return None
    kinds = [m.loc.kind for m in measured]
    if len(measured) != 1 or kinds[0] not in paired_kinds() or propose is None:
        log.warning(
            "the no-change null needs one localizer that ranks inside a paired frame (%s); this "
            "run's are %s: calibrated within the run instead ([detect] calibration)",
            " or ".join(paired_kinds()),
            ", ".join(kinds),
        )
        return None
    nc = opt.null
    moves = run_moves(run_entries or []) if nc.moves == "run" else None
    choice = null_choice(frames, map_session, nc, p.cfg.pairs.by)
    null = null_pairs(frames, choice, propose(choice.query_frames(frames.df)), nc, moves)
    if not len(null.pairs.df):
        log.warning("the map %s has no frame to draw a null from: calibrated within the run",
                    map_session)  # fmt: skip
        return None
    log.info("no-change null: %d %s pairs from the map's frames (%s)", len(null.pairs.df),
             null.construction, map_session)  # fmt: skip
    mine = {map_session: null.proposals}
    ranks = localizer_ranks(p, measured[0].loc, null.frames, null.pairs, mine)
    built = p.ran.get("detect-null", 0)
    entries = p.units("detect-null", chunks(ranks, null.frames.df))
    built = p.ran.get("detect-null", 0) - built
    if not built:
        log.info("no-change null: its %d chunks reused from the cache (the same map, pairs and "
                 "detector)", len(entries))  # fmt: skip
    fr = pd.concat([read_cached_parquet(e.path / "frames.parquet") for e in entries])
    bx = pd.concat([read_cached_parquet(e.path / "boxes.parquet") for e in entries])
    boxes = bx.loc[bx["kind"] == "detection", "score"].to_numpy(np.float64)
    scores = fr["score"].to_numpy(np.float64)
    rec = null_record(nc, null, scores, len(boxes), moves)
    rec["chunks"] = {"scored_now": built, "reused": len(entries) - built}
    return NullScores(scores, boxes, rec, tuple(e.path.name for e in entries))


def _thin_boxes(p: Any, entries: list[Any]) -> int:
    """Candidates thinner than ``[detect] min_box_side``, dropped before NMS and Table D."""
    return sum(
        int(p.cache.manifest("detect", e.key)["info"].get("thin_boxes_dropped", 0)) for e in entries
    )


def _alignment(
    out: Path, measured: list[Any], frames: pd.DataFrame | None = None, sessions: Any = ()
) -> tuple[pd.DataFrame | None, dict[str, Any]]:
    """The local localizer's alignments and what ``detect.json`` says of them (method §13.3).

    Returns the pairs' alignments (None without a local localizer) and the record's
    ``alignment`` (pairs by method) and ``local_counts`` (subimages ranked and dropped, by
    reason). Without one, an ``alignment.csv`` that an earlier run here recorded is removed.
    """
    al = measured[0].ranks.alignment if len(measured) == 1 else None
    if al is None:
        old = out / "detect.json"
        if old.is_file() and "alignment" in json.loads(old.read_text()):
            (out / "alignment.csv").unlink(missing_ok=True)
        return None, {}
    if frames is not None and len(al):  # each pair's image files, by name, beside its keys
        name = {  # a folder's frame by its file name (method §13.2), a log's by its stored image
            (str(r.session), str(r.camera), int(r.utime)): ImageRef.parse(r.image).name
            for r in frames[[*FRAME_KEY, "image"]].itertuples(index=False)
        }
        folder_names = session_names(sessions) if sessions else None
        if folder_names is not None and len(folder_names):
            name.update({
                (str(r.session), str(r.camera), int(r.utime)): str(r.name)
                for r in folder_names.itertuples(index=False)
            })  # fmt: skip
        al = al.copy()
        q_keys = al[["q_session", "q_camera", "q_utime"]].itertuples(index=False)
        al.insert(3, "q_image", [name.get((str(a), str(b), int(c)), "") for a, b, c in q_keys])
        al.insert(len(al.columns), "r_image", [
            name.get((str(a), str(b), int(c)), "")
            for a, b, c in al[["r_session", "r_camera", "r_utime"]].itertuples(index=False)
        ])  # fmt: skip
    kind = str(getattr(measured[0].loc, "kind", ""))
    return al, {
        "alignment": _write_alignment(out, al, kind),
        "local_counts": next(iter(measured[0].ranks.counts.values()), {}),
    }


def _write_alignment(out: Path, al: pd.DataFrame, kind: str = "local") -> dict[str, int]:
    """``alignment.csv`` (each pair's method, inliers and score) and its counts by method.

    A pair no link of the local chain accepts is ``none``: its query frame gets no rank, so no box
    and no score (method §13.3); a keypoint pair with too few matches for a geometry is ``none``
    too, and every ratio-test match of it counts as localized. A WARNING line counts them.
    """
    write_text(out / "alignment.csv", al.to_csv(index=False, float_format="%.6g"))
    counts = {str(k): int(v) for k, v in al["align"].value_counts().sort_index().items()}
    if counts.get("none"):
        what = (
            "no epipolar geometry could be fitted (too few matches): every match they have "
            "counts as localized"
            if kind == "keypoints"
            else "could not be aligned: their query frames carry no change score and no box"
        )
        log.warning("%d of %d pairs: %s (alignment.csv lists them)", counts["none"], len(al), what)
    return counts


def detect_pairs(
    p: Any, map_session: str, query_sessions: list[str]
) -> tuple[dict[str, Any], Any, Any, Any]:
    """Ingest, frames, annotations and the pairs by pose of the queries with the map alone."""
    ingested, frames, ann, pairs_all = until_pairs(p)
    sel = (pairs_all.df["r_session"] == map_session) & pairs_all.df["q_session"].isin(
        query_sessions
    )
    pairs = Table(
        pairs_all.df[sel].reset_index(drop=True),
        pair_keys.selected("detect-pairs", pairs_all.key, map_session, query_sessions),
    )
    if not len(pairs.df):
        raise HarnessError(
            f"detect: no frame of {query_sessions} found a map frame of {map_session} within "
            "[pairs] max_distance_m and max_yaw_diff_deg"
        )
    return ingested, frames, ann, pairs

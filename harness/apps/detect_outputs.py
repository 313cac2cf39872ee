"""``harness detect``'s outputs: frames, detections, alarms, Table D, LoC maps, page, JSON."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.apps.detect_tables import write_pixel_table, write_table_d
from harness.detect.calibrate import Alarms, alarms_of, exceedance
from harness.detect.chunk import FRAME_RESULT
from harness.evaluate.box_ap import coco_results
from harness.fusion.fuse import loc_map
from harness.imagestore import ImageRef, read_image
from harness.ingest.names import session_names, with_names
from harness.localizers.config import ALL_LOCALIZERS
from harness.records import CHANGE_CATEGORY, FRAME_KEY, QUERY_KEY, frame_keys
from harness.reports.detect_figures import trajectory_figure
from harness.reports.detect_page import write_detect_page
from harness.reports.detect_run import DetectRun
from harness.reports.overlay import colour_bar, drawn_boxes, frame_drawn_boxes
from harness.runtime.cache import (
    read_cached_parquet,
    write_json,
    write_parquet,
    write_text,
)

log = logging.getLogger(__name__)


#: What a pair not made by pose adds to its query frame's row (method §13.2).
PAIR_EXTRA = ("pair_confidence", "uncertain_pair")


def _frame_name(s: str, c: str, u: int) -> str:
    return f"{s}_{c}_{u}"


def _frame_table(
    out: Path,
    fr: pd.DataFrame,
    frames: pd.DataFrame,
    pairs: pd.DataFrame,
    names: pd.DataFrame,
    sources: dict[str, str],
    min_pair_confidence: float = 0.0,
) -> tuple[pd.DataFrame, dict[tuple[str, str, int], int]]:
    """The query frames with pose, image and map frame, numbered; ``images.json`` (COCO).

    Frames read from folders keep their file names (method §13.2): ``name`` (the query image's)
    and ``r_name`` (its map image's) columns, and the COCO ``file_name`` (with ``path``, the
    file itself); a log's frame keeps the stored image as its ``file_name``. Pairs not made by
    pose carry their ``pair_confidence``, and ``uncertain_pair`` where it is below
    ``min_pair_confidence``.

    Returns the frames and the COCO image id of each frame key.
    """
    fr = fr.merge(frames[[*FRAME_KEY, "x", "y", "yaw", "image", "width", "height"]], on=FRAME_KEY)
    extra = [c for c in PAIR_EXTRA[:1] if c in pairs.columns]
    fr = fr.merge(
        pairs[[*QUERY_KEY, "r_camera", "r_utime", *extra]].rename(
            columns={"q_session": "session", "q_camera": "camera", "q_utime": "utime"}
        ),
        on=FRAME_KEY,
        how="left",
    )
    if "pair_confidence" in fr.columns:
        fr["uncertain_pair"] = fr["pair_confidence"].to_numpy(np.float64) < min_pair_confidence
    if len(names):
        fr = with_names(fr, names, FRAME_KEY, "name")
        fr = with_names(fr, names, ["r_session", "r_camera", "r_utime"], "r_name")
    fr = fr.sort_values(FRAME_KEY).reset_index(drop=True)
    fr.insert(0, "image_id", np.arange(1, len(fr) + 1))
    ids = {(s, c, int(u)): int(i) for i, s, c, u in fr[["image_id", *FRAME_KEY]].to_numpy()}
    images = [
        {
            "id": int(r.image_id),
            "file_name": getattr(r, "name", "") or ImageRef.parse(r.image).path,
            **(
                {"path": str(Path(sources[str(r.session)]) / str(r.name))}
                if getattr(r, "name", "")
                else {}
            ),
            "width": int(r.width),
            "height": int(r.height),
            "session": str(r.session),
            "camera": str(r.camera),
            "utime": int(r.utime),
            "rotation": ImageRef.parse(r.image).rotation,
        }
        for r in fr.itertuples()
    ]
    write_json(
        out / "images.json",
        {"images": images, "categories": [{**CHANGE_CATEGORY, "supercategory": "change"}]},
    )
    return fr, ids


def _calibrated(
    fr: pd.DataFrame, dets: pd.DataFrame, entries: list[Any], null: Any
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Calibrated scores (docs/decisions.md, *Calibrated alarms*), in ``exceedance`` columns.

    Against the no-change null (``null``, :class:`harness.detect.null.NullScores`): each frame
    against the null frames, each change box against the null frames' change boxes. Within the
    run (``null`` None): each box against every candidate box of the run, one chunk at a time,
    each frame against every frame.
    """
    if null is not None:
        box_null, frame_null = null.boxes, null.frames
    else:
        box_null = np.concatenate(
            [read_cached_parquet(e.path / "candidates.parquet")["loc"].to_numpy() for e in entries]
            or [np.zeros(0)]
        )
        frame_null = fr["score"].to_numpy()
    dets = dets.assign(
        exceedance=np.where(
            dets["kind"] == "detection", exceedance(box_null, dets["score"].to_numpy()), np.nan
        )
    )
    fr = fr.assign(exceedance=exceedance(frame_null, fr["score"].to_numpy()))
    return fr, dets


def _write_alarms(out: Path, al: Alarms) -> None:
    """``alarms.csv``: the frames and boxes flagged at the nominal false-alarm rate.

    :func:`harness.detect.calibrate.alarms_of`'s: a frame whose pair is not comparable (and its
    boxes) raises no alarm; a box raises one only where its frame does.
    """
    alarms = pd.concat(
        [
            al.frames.assign(kind="frame")[["kind", *FRAME_KEY, "score", "exceedance"]],
            al.boxes.assign(kind="box")[
                ["kind", *FRAME_KEY, "x1", "y1", "x2", "y2", "score", "exceedance"]
            ],
        ],
        ignore_index=True,
    ).sort_values(["kind", "exceedance", *FRAME_KEY, "x1", "y1"], kind="stable")
    write_text(out / "alarms.csv", alarms.to_csv(index=False, float_format="%.6g"))


def _drawn(out: Path, dets: pd.DataFrame, fr: pd.DataFrame) -> pd.DataFrame:
    """``dets`` with ``drawn`` (:func:`harness.reports.overlay.drawn_boxes`), to a CSV.

    ``drawn_boxes.csv``: the list the page's thumbnails and the LoC overlays draw from.
    """
    det = dets[dets["kind"] == "detection"]
    shown = [np.asarray(drawn_boxes(g).index) for _, g in det.groupby(FRAME_KEY, sort=True)]
    dets = dets.assign(drawn=dets.index.isin(np.concatenate([[], *shown])))
    rows = dets[dets["drawn"]].merge(fr[[*FRAME_KEY, *fr.columns.intersection(["name"])]])
    cols = [c for c in (*FRAME_KEY, "name", "rank", "x1", "y1", "x2", "y2", "score", "alarmed")
            if c in rows.columns]  # fmt: skip
    write_text(out / "drawn_boxes.csv", rows[cols].to_csv(index=False, float_format="%.6g"))
    return dets


def _frame_columns(fr: pd.DataFrame) -> list[str]:
    """The columns of ``frames.parquet`` / ``frames.csv``.

    With file names and pair confidence where the frames have them (method §13.2).
    """
    named = [c for c in ("name", "r_name", *PAIR_EXTRA) if c in fr.columns]
    where = ["x", "y", "yaw", "r_session", "r_camera", "r_utime"]
    return ["image_id", *FRAME_KEY, *where, *named, *FRAME_RESULT, "exceedance"]


@dataclass(frozen=True)
class DetectResult:
    """One ``harness detect`` run as its outputs hold it, for what prints it.

    ``record``: ``detect.json``; ``frames``: ``frames.parquet``'s rows; the tables' Markdown
    (``tableD.md``, ``tableD_pixel.md``), None where the run has no annotations or masks.
    """

    record: dict[str, Any]
    frames: pd.DataFrame
    table_d_markdown: str | None = None
    pixel_markdown: str | None = None


@dataclass(frozen=True)
class Scored:
    """A run's frames and boxes once calibrated, counted and written (:func:`scored`).

    ``fr``: the frame rows, numbered and calibrated, with ``alarmed``; ``dets``: every box of the
    chunks, calibrated, with ``comparable``, ``alarmed`` and ``drawn``; ``ids``: each frame key's
    COCO image id; ``table``: ``frames.parquet``'s rows; ``not_comparable``: ``detect.json``'s.
    """

    fr: pd.DataFrame
    dets: pd.DataFrame
    ids: dict[tuple[str, str, int], int]
    table: pd.DataFrame
    detections: int
    alarms: Alarms
    not_comparable: dict[str, Any]


def write_outputs(run: DetectRun, dets: pd.DataFrame, fr: pd.DataFrame) -> DetectResult:
    """Everything a detect run writes, step by step, and what the command prints of it.

    ``dets`` and ``fr`` are the chunks' boxes and frame rows: calibrated and written with their
    alarms at the nominal false-alarm rate ``run.alarm`` (:func:`scored`), then the most changed
    frames' LoC maps and the map (:func:`figures`), Table D and its pixel part where there are
    annotations or masks, the page, and ``detect.json``'s record (:func:`run_record`).
    """
    cfg, out = run.cfg, run.p.out
    s = scored(run, dets, fr)
    top, maps, traj = figures(run, s)
    scored_d = write_table_d(run, s.fr, s.dets, s.ids) if len(run.ann) else None
    table_d, table_d_md = scored_d or (None, None)
    names = session_names(cfg.sessions)
    pixel, pixel_md = write_pixel_table(
        out, cfg, names, run.map_session, run.entries, s.fr, run.frames, run.opt
    )
    page = write_detect_page(run, (s.fr, top, s.dets), maps, (table_d, pixel), s.alarms.record())
    written = {
        "detections": str(out / "detections.json"),
        "images": str(out / "images.json"),
        "frames": str(out / "frames.parquet"),
        "trajectory": str(traj),
        "page": str(page),
        "locmaps": [str(m) for m in maps.values()],
    }
    record = run_record(run, s, written, (table_d, pixel))
    return DetectResult(record, s.table, table_d_md, pixel_md)


def _sure(fr: pd.DataFrame) -> np.ndarray:
    """The frames whose pair is not uncertain (method §13.2; all where pairs are by pose)."""
    if "uncertain_pair" in fr.columns:
        return ~fr["uncertain_pair"].to_numpy(bool)
    return np.ones(len(fr), bool)


def scored(run: DetectRun, dets: pd.DataFrame, fr: pd.DataFrame) -> Scored:
    """The frames and boxes calibrated, counted and written.

    ``images.json``, ``detections.json``, ``frames.*``, ``alarms.csv``, ``drawn_boxes.csv``.
    """
    cfg, out = run.cfg, run.p.out
    names = session_names(cfg.sessions)
    sources = {sc.name: sc.source for sc in cfg.sessions}
    fr, ids = _frame_table(
        out, fr, run.frames, run.pairs, names, sources, cfg.pairs.min_pair_confidence
    )
    fr, dets = _calibrated(fr, dets, run.entries, run.null)
    comparable = pd.MultiIndex.from_frame(fr.loc[fr["comparable"].astype(bool), FRAME_KEY])
    dets = dets.assign(comparable=pd.MultiIndex.from_frame(dets[FRAME_KEY]).isin(comparable))
    det = dets[dets["kind"] == "detection"]
    keys = frame_keys(det)
    results = coco_results(  # with their calibrated scores
        [ids[k] for k in keys], det[["x1", "y1", "x2", "y2"]].to_numpy(), det["score"].tolist(),
        exceedance=det["exceedance"].astype(float).tolist(),
        comparable=det["comparable"].astype(bool).tolist(),
    )  # fmt: skip
    write_text(out / "detections.json", json.dumps(results))
    table = fr[_frame_columns(fr)]
    write_parquet(out / "frames.parquet", table)
    write_text(out / "frames.csv", table.to_csv(index=False, float_format="%.6g"))
    al = alarms_of(fr, det, run.alarm)  # the one count of alarms (method §13.1)
    _write_alarms(out, al)
    fr["alarmed"] = fr.index.isin(al.frames.index)
    dets = dets.assign(alarmed=dets.index.isin(al.boxes.index))
    dets = _drawn(out, dets, fr)  # what the page and the overlays draw of them
    not_comparable = _not_comparable(fr, run.opt.not_comparable)
    return Scored(fr, dets, ids, table, len(results), al, not_comparable)


def figures(run: DetectRun, s: Scored) -> tuple[pd.DataFrame, dict[Any, Path], Path]:
    """The ``[detect] top`` most changed frames, their LoC maps and the trajectory figure.

    The most changed are of the frames whose pair is sure and comparable and that have a score.
    """
    fr, out = s.fr, run.p.out
    comparable = fr["comparable"].astype(bool).to_numpy()
    top = fr[_sure(fr) & comparable & np.isfinite(fr["score"].to_numpy(np.float64))]
    top = top.sort_values(["score", "image_id"], ascending=[False, True]).head(run.opt.top)
    maps = locmaps(out, top, run.entries, s.dets)
    traj = trajectory_figure(out / "trajectory.png", run.frames, run.map_session, fr, top)
    return top, maps, traj


def run_record(
    run: DetectRun, s: Scored, written: dict[str, Any], tables: tuple[Any, Any]
) -> dict[str, Any]:
    """``detect.json``'s record: options, counts, alarms, calibration, outputs and tables.

    ``tables``: Table D and its pixel part, None where not computed.
    """
    cfg, opt, p = run.cfg, run.opt, run.p
    table_d, pixel = tables
    return {
        "config": cfg.name,
        "map": run.map_session,
        "queries": run.queries,
        "localizers": run.localizers,
        # the folders' names, the map's first, where the sessions are folders of images
        "folders": run.folders or None,
        "fused_across": ALL_LOCALIZERS if len(run.localizers) > 1 else None,
        "options": opt.record(cfg.fusion.seed, cfg.proposals.segments),
        "query_frames": len(s.fr),
        # method §13.2: pairs under [pairs] min_pair_confidence, left out of the most-changed list
        "uncertain_pairs": int((~_sure(s.fr)).sum()),
        "min_pair_confidence": cfg.pairs.min_pair_confidence,
        # docs/decisions.md, *The plain difference*: pairs that could not be registered
        "not_comparable": s.not_comparable,
        "detections": s.detections,
        # method §13.1: what the nominal false-alarm rate flags (alarms.csv)
        "alarm": s.alarms.record(),
        # what the calibrated scores are measured against: the no-change null or the run itself
        "calibration": run.null.record if run.null is not None else {"method": "within-run"},
        "outputs": written,
        "table_d": table_d.to_dict(orient="records") if table_d is not None else None,
        # method §13.2: the LoC maps' pixel AP against the masks (tableD_pixel.csv)
        "table_d_pixel": pixel.to_dict(orient="records") if pixel is not None else None,
        "stage_units_run": p.ran,
        "timings_s": {k: round(v, 3) for k, v in p.timings.items()},
    }


def _not_comparable(fr: pd.DataFrame, policy: str) -> dict[str, Any]:
    """``detect.json``'s ``not_comparable``, and a WARNING line naming the frames.

    A pair that cannot be registered is not comparable: with ``[detect] not_comparable = "drop"``
    its query frame has no change box, no score and no alarm, and is never among the most changed.
    """
    bad = fr[~fr["comparable"].astype(bool)]
    label = (
        bad["name"] if "name" in bad.columns else bad["session"] + "/" + bad["utime"].astype(str)
    )
    names = [str(x) for x in label]
    reasons = {str(k): int(v) for k, v in bad["not_comparable_why"].str.replace(
        r" \(.*", "", regex=True).value_counts().sort_index().items()}  # fmt: skip
    if len(bad) and len(bad) == len(fr):
        log.warning(
            "no pair of this run could be registered (%s): %s; no frame raises an alarm and none "
            "is listed as most changed",
            "; ".join(f"{k}: {v}" for k, v in reasons.items()),
            "every change box rests on a comparison without keypoints (an affine fit of the "
            "intensities, or the frames as they stand) and is marked comparable = false"
            if policy == "fallback"
            else "no change box is drawn" if policy == "drop"
            else "every change box is the localizer's alone, marked comparable = false",
        )  # fmt: skip
    elif len(bad):
        shown = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
        log.warning(
            "%d of %d pairs are not comparable (could not be registered: %s): %s; %s",
            len(bad), len(fr), "; ".join(f"{k}: {v}" for k, v in reasons.items()), shown,
            "no change box, score or alarm there" if policy == "drop"
            else "their boxes are kept, marked comparable = false in frames.csv",
        )  # fmt: skip
    return {"frames": len(bad), "of_frames": len(fr), "policy": policy, "reasons": reasons,
            "names": names}  # fmt: skip


def locmaps(
    out: Path, top: pd.DataFrame, entries: list[Any], dets: pd.DataFrame
) -> dict[tuple[str, str, int], Path]:
    """LoC maps of the ``top`` frames: float16 ``.npy`` and a colour overlay with its bar."""
    want = set(map(tuple, top[FRAME_KEY].to_numpy().tolist()))
    d = out / "locmaps"
    d.mkdir(exist_ok=True)
    written: dict[tuple[str, str, int], Path] = {}
    for e in entries:
        s = read_cached_parquet(e.path / "samples.parquet")
        for key, g in s.groupby(QUERY_KEY, sort=True):
            k = (str(key[0]), str(key[1]), int(key[2]))
            if k not in want:
                continue
            r = top[(top["session"] == k[0]) & (top["camera"] == k[1]) & (top["utime"] == k[2])]
            img = read_image(str(r["image"].iloc[0]))
            h, w = img.shape[:2]
            m = loc_map(
                g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64),
                g["loc"].to_numpy(np.float64),
                w,
                h,
            )
            name = _frame_name(*k)
            np.save(d / f"{name}.npy", m.astype(np.float16))
            lo, hi = float(np.nanmin(m)), float(np.nanmax(m))
            norm = np.nan_to_num((m - lo) / (hi - lo) if hi > lo else np.zeros_like(m))
            heat = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]
            over = (0.45 * img + 0.55 * heat).astype(np.uint8)
            over[~np.isfinite(m)] = img[~np.isfinite(m)]
            for x1, y1, x2, y2 in frame_drawn_boxes(dets, k):
                cv2.rectangle(
                    over, (int(x1), int(y1)), (int(x2) - 1, int(y2) - 1), (0, 255, 255), 1
                )
            up = max(1, int(np.ceil(240 / w)))  # small frames: enlarged so the bar is legible
            big = cv2.resize(over, (w * up, h * up), interpolation=cv2.INTER_NEAREST)
            panel = np.vstack([big, colour_bar(w * up, lo, hi)])
            cv2.imwrite(str(d / f"{name}.png"), panel[..., ::-1])
            written[k] = d / f"{name}.png"
    return written

"""``harness detect``'s outputs: frames, detections, alarms, Table D, LoC maps, page, JSON."""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.boxes import FrameNMS
from harness.config.schema import Config
from harness.detect.calibrate import Alarms, alarms_of, exceedance
from harness.detect.chunk import FRAME_RESULT
from harness.detect.pixels import mask_frames, masked_frame, pair_difference
from harness.errors import AnnotationError
from harness.evaluate.box_ap import coco_results
from harness.evaluate.chance import ChanceSettings
from harness.evaluate.table_d import TableDInputs, score_detections
from harness.evaluate.table_d_pixel import pixel_table
from harness.fusion.fuse import loc_map
from harness.imagestore import ImageRef, read_image
from harness.ingest.names import session_names, with_names
from harness.localizers.config import ALL_LOCALIZERS
from harness.records import CHANGE_CATEGORY, FRAME_KEY, QUERY_KEY, frame_keys
from harness.reports.detect_figures import trajectory_figure
from harness.reports.detect_page import write_detect_page
from harness.reports.detect_run import DetectRun
from harness.reports.overlay import colour_bar, drawn_boxes, frame_drawn_boxes
from harness.reports.table_d import table_d_markdown
from harness.reports.table_dp import pixel_markdown
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


def _table_d(
    run: DetectRun, fr: pd.DataFrame, dets: pd.DataFrame, ids: dict[tuple[str, str, int], int]
) -> tuple[pd.DataFrame, str] | None:
    """Table D on the annotated frames, from the candidates of those frames only, and its text."""
    out, cfg, ann, entries, opt = run.p.out, run.cfg, run.ann, run.entries, run.opt
    annotated = pd.MultiIndex.from_frame(ann[FRAME_KEY].drop_duplicates())
    cands, plain = [], []
    for e in entries:  # candidates of the annotated frames only, one chunk at a time
        sm = read_cached_parquet(e.path / "candidates.parquet")  # the generator's boxes
        cands.append(sm[pd.MultiIndex.from_frame(sm[QUERY_KEY]).isin(annotated)])
        if (e.path / "plain_difference.parquet").is_file():
            pd_ = read_cached_parquet(e.path / "plain_difference.parquet")
            plain.append(pd_[pd.MultiIndex.from_frame(pd_[QUERY_KEY]).isin(annotated)])
    nms = FrameNMS(opt.nms_iou, opt.max_boxes)  # each frame's overlaps made once for the draws
    groups = _groups(fr, run.frames) if opt.bootstrap_group == "map_image" else None
    inputs = TableDInputs(
        fr, ann, dets, ids, pd.concat(cands, ignore_index=True), nms,
        pd.concat(plain, ignore_index=True) if plain else None, groups, opt.bootstrap_group,
        opt.difference.recipe,
    )  # fmt: skip
    t = score_detections(out, inputs, ChanceSettings.of(cfg), opt.boxes, run.alarm)
    if t is None:
        return None
    md = table_d_markdown(t)
    write_text(out / "tableD.md", md)
    return t, md


def _groups(fr: pd.DataFrame, frames: pd.DataFrame) -> dict[tuple[str, str, int], str]:
    """Each query frame's bootstrap group: its map image (``[detect] bootstrap_group``).

    Map frames whose image files hold the same bytes are one group (a folder may hold one view
    under several names), so are query frames paired with one map frame.
    """
    image = frames.set_index(FRAME_KEY)["image"]
    digest: dict[str, str] = {}
    out = {}
    for r in fr[[*FRAME_KEY, "r_session", "r_camera", "r_utime"]].itertuples(index=False):
        mk = (str(r.r_session), str(r.r_camera), int(r.r_utime))
        uri = str(image.get(mk, "")) if mk in image.index else ""
        if uri not in digest:
            ref = ImageRef.parse(uri)
            try:
                digest[uri] = hashlib.sha1(Path(ref.path).read_bytes()).hexdigest() + ref.fragment
            except OSError:  # no file (a log's stored frame): the map frame itself
                digest[uri] = "|".join(map(str, mk))
        out[(str(r.session), str(r.camera), int(r.utime))] = digest[uri] if uri else str(mk)
    return out


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


def write_outputs(run: DetectRun, dets: pd.DataFrame, fr: pd.DataFrame) -> DetectResult:
    """COCO files, the frame table, LoC maps of the most changed frames, the map, Table D, page.

    ``dets`` and ``fr`` are the chunks' boxes and frame rows. Also the alarms at the nominal
    false-alarm rate ``run.alarm`` (``alarms.csv``, method §13.1).
    """
    p, cfg, opt, map_session, queries = run.p, run.cfg, run.opt, run.map_session, run.queries
    frames, pairs, ann, entries, alarm = run.frames, run.pairs, run.ann, run.entries, run.alarm
    out = p.out
    names = session_names(cfg.sessions)
    sources = {sc.name: sc.source for sc in cfg.sessions}
    fr, ids = _frame_table(out, fr, frames, pairs, names, sources, cfg.pairs.min_pair_confidence)
    fr, dets = _calibrated(fr, dets, entries, run.null)
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
    al = alarms_of(fr, det, alarm)  # the one count of alarms (method §13.1)
    _write_alarms(out, al)
    fr["alarmed"] = fr.index.isin(al.frames.index)
    dets = dets.assign(alarmed=dets.index.isin(al.boxes.index))
    dets = _drawn(out, dets, fr)  # what the page and the overlays draw of them
    sure = ~fr["uncertain_pair"] if "uncertain_pair" in fr.columns else np.ones(len(fr), bool)
    comparable = fr["comparable"].astype(bool).to_numpy()
    not_comparable = _not_comparable(fr, opt.not_comparable)
    top = fr[sure & comparable & np.isfinite(fr["score"].to_numpy(np.float64))]
    top = top.sort_values(["score", "image_id"], ascending=[False, True]).head(opt.top)
    maps = locmaps(out, top, entries, dets)

    traj = trajectory_figure(out / "trajectory.png", frames, map_session, fr, top)
    table_d, table_d_md = (_table_d(run, fr, dets, ids) if len(ann) else None) or (None, None)
    pixel, pixel_md = write_pixel_table(out, cfg, names, map_session, entries, fr, frames, opt)

    page = write_detect_page(run, (fr, top, dets), maps, (table_d, pixel), al.record())
    record = {
        "config": cfg.name,
        "map": map_session,
        "queries": queries,
        "localizers": run.localizers,
        # the folders' names, the map's first, where the sessions are folders of images
        "folders": run.folders or None,
        "fused_across": ALL_LOCALIZERS if len(run.localizers) > 1 else None,
        "options": opt.record(cfg.fusion.seed, cfg.proposals.segments),
        "query_frames": len(fr),
        # method §13.2: pairs under [pairs] min_pair_confidence, left out of the most-changed list
        "uncertain_pairs": int((~sure).sum()),
        "min_pair_confidence": cfg.pairs.min_pair_confidence,
        # docs/decisions.md, *The plain difference*: pairs that could not be registered
        "not_comparable": not_comparable,
        "detections": len(results),
        # method §13.1: what the nominal false-alarm rate flags (alarms.csv)
        "alarm": al.record(),
        # what the calibrated scores are measured against: the no-change null or the run itself
        "calibration": run.null.record if run.null is not None else {"method": "within-run"},
        "outputs": {
            "detections": str(out / "detections.json"),
            "images": str(out / "images.json"),
            "frames": str(out / "frames.parquet"),
            "trajectory": str(traj),
            "page": str(page),
            "locmaps": [str(m) for m in maps.values()],
        },
        "table_d": table_d.to_dict(orient="records") if table_d is not None else None,
        # method §13.2: the LoC maps' pixel AP against the masks (tableD_pixel.csv)
        "table_d_pixel": pixel.to_dict(orient="records") if pixel is not None else None,
        "stage_units_run": p.ran,
        "timings_s": {k: round(v, 3) for k, v in p.timings.items()},
    }
    return DetectResult(record, table, table_d_md, pixel_md)


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


def write_pixel_table(
    out: Path,
    cfg: Config,
    names: pd.DataFrame,
    map_session: str,
    entries: list[Any],
    run_frames: pd.DataFrame,
    frames_table: pd.DataFrame,
    opt: Any = None,
) -> tuple[pd.DataFrame | None, str | None]:
    """``tableD_pixel.csv`` / ``.md`` from ``[masks] folder``'s masks of this run's query frames.

    ``run_frames``: the run's frame rows (each query frame's map frame, ``r_*``);
    ``frames_table``: every frame's image, for the plain-difference row; ``opt``: the run's
    ``[detect]`` (the config's where None), whose registration that row uses.

    ``entries`` are the detect chunks (their ``samples.parquet``: boxes and ``loc``), read one at
    a time for the masked frames only; a masked frame without a sample box counts all its pixels
    uncovered. (None, None) where no mask names a frame of the run (and an earlier run's table in
    ``out`` is removed).
    """
    files: dict[tuple[str, str, int], Path] = {}
    if cfg.masks.folder is not None:
        ran = set(map(tuple, run_frames[FRAME_KEY].to_numpy().tolist()))
        every = mask_frames(Path(cfg.masks.folder), names, [map_session])
        files = {k: f for k, f in every.items() if k in ran}
        if len(files) < len(every):  # e.g. frames thinned out by [pairs] stride_m
            log.info(
                "pixel AP: %d of %d masks name a frame this run did not detect on, left out",
                len(every) - len(files),
                len(every),
            )
    if not files:  # an earlier run's table into this run directory is not this run's
        for stale in ("tableD_pixel.csv", "tableD_pixel.md"):
            (out / stale).unlink(missing_ok=True)
        return None, None
    boxes: dict[tuple[str, str, int], tuple[np.ndarray, np.ndarray]] = {}
    images = frames_table.set_index(FRAME_KEY)["image"]
    want = pd.MultiIndex.from_tuples(sorted(files))
    for e in entries:
        s = read_cached_parquet(e.path / "samples.parquet")
        s = s[pd.MultiIndex.from_frame(s[QUERY_KEY]).isin(want)]
        for key, g in s.groupby(QUERY_KEY, sort=True):
            k = (str(key[0]), str(key[1]), int(key[2]))
            boxes[k] = (
                g[["x1", "y1", "x2", "y2"]].to_numpy(np.float64),
                g["loc"].to_numpy(np.float64),
            )
    frames = []
    for k in sorted(files):
        b, loc = boxes.get(k, (np.zeros((0, 4)), np.zeros(0)))
        mask = cv2.imread(str(files[k]), cv2.IMREAD_UNCHANGED)
        if mask is None:  # read as annotations a moment ago: changed on disk since
            raise AnnotationError(f"{files[k]}: not a readable mask image")
        diff = pair_difference(run_frames, images, k, b, opt or cfg.detect)
        frames.append(masked_frame(b, loc, mask, diff))
    r = cfg.report
    t = pixel_table(frames, r.chance_draws, r.bootstrap, r.ci, cfg.seed, r.min_positive_images)
    write_text(out / "tableD_pixel.csv", t.to_csv(index=False, float_format="%.4f"))
    md = pixel_markdown(t)
    write_text(out / "tableD_pixel.md", md)
    return t, md

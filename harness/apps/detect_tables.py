"""Table D and its pixel part as a detect run writes them (method §13.1, 13.2).

The figures are computed where the other tables are (``evaluate/table_d.py``,
``evaluate/table_d_pixel.py``) and rendered where they are (``reports/table_d.py``,
``reports/table_dp.py``); this reads the run's chunks for them and writes the files.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.boxes import FrameNMS
from harness.config.schema import Config
from harness.detect.pixels import mask_frames, masked_frame, pair_difference
from harness.errors import AnnotationError
from harness.evaluate.chance import ChanceSettings
from harness.evaluate.table_d import TableDInputs, score_detections
from harness.evaluate.table_d_pixel import pixel_table
from harness.imagestore import ImageRef
from harness.records import FRAME_KEY, QUERY_KEY
from harness.reports.detect_run import DetectRun
from harness.reports.table_d import table_d_markdown
from harness.reports.table_dp import pixel_markdown
from harness.runtime.cache import read_cached_parquet, write_text

log = logging.getLogger(__name__)


def write_table_d(
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
    groups = bootstrap_groups(fr, run.frames) if opt.bootstrap_group == "map_image" else None
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


def bootstrap_groups(fr: pd.DataFrame, frames: pd.DataFrame) -> dict[tuple[str, str, int], str]:
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

"""Annotations to and from labelling tools (method §10).

COCO, Pascal VOC and CVAT boxes imported into the harness's CSV, and the query frames exported
for labelling.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from harness.errors import AnnotationError
from harness.imagestore import read_image
from harness.ingest.annotations import (
    COLUMNS,
    image_name,
    no_change_row,
    parse_image_name,
    validate_annotations,
)
from harness.inputs import check_input, read_text
from harness.records import CHANGE_CATEGORY, FRAME_KEY, QUERY_KEY
from harness.runtime.cache import atomic_dir, atomic_path, write_json
from harness.runtime.outdirs import check_file_replaceable, check_replaceable, write_marker


def _rows_for_image(
    name: str, boxes: list[tuple[float, float, float, float, str]], where: str
) -> list[dict]:
    s, c, t = parse_image_name(name, where)
    if not boxes:
        return [no_change_row(s, c, t)]
    return [
        dict(session=s, camera=c, utime=t, status="change", x1=x1, y1=y1, x2=x2, y2=y2, label=lab)
        for x1, y1, x2, y2, lab in boxes
    ]


def import_coco(path: Path) -> pd.DataFrame:
    """COCO JSON: ``bbox`` is ``[x, y, w, h]``; an image without annotations is no-change."""
    text = read_text(path, "COCO annotation file", AnnotationError)
    try:
        doc = json.loads(text)
        images = {im["id"]: im["file_name"] for im in doc["images"]}
        cats = {c["id"]: c["name"] for c in doc.get("categories", [])}
        per: dict[int, list] = {i: [] for i in images}
        for a in doc.get("annotations", []):
            x, y, w, h = (float(v) for v in a["bbox"])
            if a["image_id"] not in per:
                raise AnnotationError(
                    f"{path}: annotation {a.get('id')} refers to unknown image_id {a['image_id']}"
                )
            per[a["image_id"]].append((x, y, x + w, y + h, cats.get(a.get("category_id"), "")))
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise AnnotationError(
            f"{path}: not a COCO annotation file: {type(err).__name__}: {err}"
        ) from None
    rows = [
        r
        for i, name in sorted(images.items())
        for r in _rows_for_image(name, per[i], f"{path}: image {i}")
    ]
    return pd.DataFrame(rows, columns=COLUMNS)


def _number(text: str | None, name: str) -> float:
    """An XML attribute or element text as a float; a missing one is a ValueError naming it."""
    if text is None:
        raise ValueError(f"no {name}")
    return float(text)


def _cvat_box(b: ET.Element) -> tuple[float, float, float, float, str]:
    """A CVAT ``<box>``: (xtl, ytl, xbr, ybr, label)."""
    x1, y1, x2, y2 = (_number(b.get(k), k) for k in ("xtl", "ytl", "xbr", "ybr"))
    return x1, y1, x2, y2, b.get("label", "")


def import_voc(folder: Path) -> pd.DataFrame:
    """Pascal VOC: one XML per image in ``folder``; an image without objects is no-change."""
    rows: list[dict] = []
    folder = check_input(folder, "VOC annotation folder", AnnotationError, directory=True)
    files = sorted(Path(folder).glob("*.xml"))
    if not files:
        raise AnnotationError(f"{folder}: no VOC .xml files")
    for f in files:
        try:
            root = ET.parse(f).getroot()
            name = root.findtext("filename") or f.stem
            boxes = []
            for obj in root.findall("object"):
                bb = obj.find("bndbox")
                if bb is None:
                    raise AnnotationError(f"{f}: object without bndbox")
                x1, y1, x2, y2 = (
                    _number(bb.findtext(k), k) for k in ("xmin", "ymin", "xmax", "ymax")
                )
                boxes.append((x1, y1, x2, y2, obj.findtext("name") or ""))
        except (ET.ParseError, TypeError, ValueError, OSError) as err:
            raise AnnotationError(f"{f}: not a VOC annotation: {err}") from None
        rows += _rows_for_image(name, boxes, str(f))
    return pd.DataFrame(rows, columns=COLUMNS)


def import_cvat(path: Path) -> pd.DataFrame:
    """CVAT for images 1.1 XML: ``<image name=...><box label xtl ytl xbr ybr/></image>``."""
    check_input(path, "CVAT annotation file", AnnotationError)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, UnicodeDecodeError) as err:
        raise AnnotationError(f"{path}: not valid XML: {err}") from None
    rows: list[dict] = []
    images = root.findall("image")
    if not images:
        raise AnnotationError(
            f"{path}: no <image> elements (is this a CVAT for images 1.1 export?)"
        )
    for im in images:
        try:
            boxes = [_cvat_box(b) for b in im.findall("box")]
        except (TypeError, ValueError) as err:
            raise AnnotationError(
                f"{path}: image {im.get('name')}: bad box attribute: {err}"
            ) from None
        rows += _rows_for_image(im.get("name", ""), boxes, f"{path}: image {im.get('id')}")
    return pd.DataFrame(rows, columns=COLUMNS)


IMPORTERS = {"coco": import_coco, "voc": import_voc, "cvat": import_cvat}


def import_annotations(
    fmt: str, src: Path, frames: pd.DataFrame | None, out: Path, force: bool = False
) -> pd.DataFrame:
    """Import, validate and write the canonical CSV.

    Written atomically; an existing ``out`` is replaced only with ``force``.
    """
    out = check_file_replaceable(Path(out), force)
    if fmt not in IMPORTERS:
        raise AnnotationError(f"unknown annotation format {fmt!r}; known: {sorted(IMPORTERS)}")
    df = validate_annotations(IMPORTERS[fmt](Path(src)).reset_index(drop=True), frames, str(src))

    with atomic_path(Path(out)) as tmp:
        df.to_csv(tmp, index=False, float_format="%.2f")
    return df


def export_for_labelling(
    pairs: pd.DataFrame,
    frames: pd.DataFrame,
    out: Path,
    limit: int | None = None,
    force: bool = False,
) -> Path:
    """Write chosen query frames beside their references for a labelling tool.

    Each image is ``query | reference`` side by side with the query on the left, so a box drawn
    on the query keeps the query's pixel coordinates (the importers reject boxes beyond the
    query's width). A COCO task file (``task.json``, images only, one category ``change``)
    lists them; CVAT, Label Studio and most tools import it.
    """
    out = check_replaceable(Path(out), "labelling-task", force)
    keyed = frames.set_index(FRAME_KEY)
    q = pairs.drop_duplicates(QUERY_KEY).head(limit) if limit else pairs.drop_duplicates(QUERY_KEY)
    for side in ("q", "r"):  # every frame a pair names must be in the frame table
        cols = [f"{side}_session", f"{side}_camera", f"{side}_utime"]
        missing = ~pd.MultiIndex.from_frame(q[cols]).isin(keyed.index)
        if missing.any():
            s_, c_, u_ = q[cols].to_numpy()[int(np.nonzero(missing)[0][0])]
            raise AnnotationError(
                f"the frame table lacks the {'query' if side == 'q' else 'reference'} frame "
                f"{s_} {c_} {u_} of a pair ({int(missing.sum())} pair(s) in all): give the frame "
                "table of the same run as the pairs"
            )
    images = []
    with atomic_dir(Path(out)) as tmp:
        (tmp / "images").mkdir()
        for i, row in enumerate(q.itertuples(index=False), 1):
            qf = keyed.loc[(row.q_session, row.q_camera, row.q_utime)]
            rf = keyed.loc[(row.r_session, row.r_camera, row.r_utime)]
            qi, ri = read_image(qf["image"]), read_image(rf["image"])
            if ri.shape[0] != qi.shape[0]:
                ri = cv2.resize(ri, (int(ri.shape[1] * qi.shape[0] / ri.shape[0]), qi.shape[0]))
            name = image_name(row.q_session, row.q_camera, row.q_utime)
            cv2.imwrite(
                str(tmp / "images" / name), cv2.cvtColor(np.hstack([qi, ri]), cv2.COLOR_RGB2BGR)
            )
            images.append(
                {
                    "id": i,
                    "file_name": name,
                    "width": int(qi.shape[1] + ri.shape[1]),
                    "height": int(qi.shape[0]),
                    "query_width": int(qi.shape[1]),
                    "reference": image_name(row.r_session, row.r_camera, row.r_utime),
                }
            )
        write_json(
            tmp / "task.json",
            {"images": images, "annotations": [], "categories": [dict(CHANGE_CATEGORY)]},
        )
        write_marker(tmp, "labelling-task", record_entries=True)
    return Path(out)

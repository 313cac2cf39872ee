"""Object proposals (qBBs), SPEC section 5.

Methods (each one modality with its own retrieval engine):

- ``grid5``: the paper's five fixed boxes.
- ``edges``: category-independent proposals from closed edge contours at several scales, scored by
  edge density (in the spirit of EdgeBoxes; no weights needed). The default unsupervised method.
- ``mser``: category-independent proposals from OpenCV's MSER regions (no weights needed).
- ``yolo``: a YOLO-family detector exported to TorchScript, loaded from a local file.
- ``file``: boxes from a table the user provides (any other detector).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from harness.config.schema import (
    EdgesConfig,
    MserConfig,
    ProposalsConfig,
    SegmentsConfig,
    YoloConfig,
)
from harness.errors import AnnotationError, ConfigError, HarnessError
from harness.imagestore import read_image
from harness.methods import (
    PROPOSER_OPTIONS,
    PROPOSERS,
    SPECIAL_PROPOSALS,
    known_proposal_methods,
)
from harness.records import FRAME_KEY
from harness.runtime.cache import source_fingerprints, write_parquet
from harness.runtime.progress import progress

log = logging.getLogger(__name__)

#: Methods with their own code path: grid5 (no pixels), yolo (batched), file (a user's table).
SPECIAL_METHODS = SPECIAL_PROPOSALS
PROPOSAL_COLUMNS = [
    "session",
    "camera",
    "utime",
    "proposal_method",
    "box_id",
    "x1",
    "y1",
    "x2",
    "y2",
    "score",
    "class",
]


def grid5(width: float, height: float) -> np.ndarray:
    """The five fixed boxes of SPEC section 5 as a (5, 4) float array ``x1, y1, x2, y2``."""
    w, h = float(width), float(height)
    return np.array(
        [
            [w / 3, h / 3, 2 * w / 3, 2 * h / 3],
            [0.0, 0.0, 2 * w / 3, 2 * h / 3],
            [w / 3, 0.0, w, 2 * h / 3],
            [0.0, h / 3, 2 * w / 3, h],
            [w / 3, h / 3, w, h],
        ],
        dtype=np.float64,
    )


def nms(
    boxes: np.ndarray, scores: np.ndarray, iou: float, classes: np.ndarray | None = None
) -> np.ndarray:
    """Indices kept by (class-aware) non-maximum suppression, highest score first; ties by index."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    xywh = np.column_stack(
        [boxes[:, 0], boxes[:, 1], boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]]
    )
    cls = np.zeros(len(boxes), np.int32) if classes is None else classes.astype(np.int32)
    kept = cv2.dnn.NMSBoxesBatched(
        xywh.tolist(), scores.astype(float).tolist(), cls.tolist(), -1e9, float(iou)
    )
    keep = np.asarray(kept, np.int64).ravel()
    order = np.lexsort((keep, -scores[keep]))
    return keep[order]


def _working_copy(rgb: np.ndarray, work_width: int) -> tuple[np.ndarray, float]:
    """``rgb`` shrunk to at most ``work_width`` pixels wide (area interpolation), and the scale."""
    h, w = rgb.shape[:2]
    scale = min(1.0, work_width / w)
    if scale >= 1:
        return rgb, scale
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), scale


def mser_boxes(rgb: np.ndarray, cfg: MserConfig) -> tuple[np.ndarray, np.ndarray]:
    """MSER region boxes in full-image pixels, scored by their area fraction; (k, 4), (k,)."""
    h, w = rgb.shape[:2]
    small, scale = _working_copy(rgb, cfg.work_width)
    gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    sa = gray.shape[0] * gray.shape[1]
    mser = cv2.MSER_create(  # type: ignore[attr-defined]  # not in OpenCV's stubs
        5, max(8, int(cfg.min_area_frac * sa * 0.3)), int(cfg.max_area_frac * sa)
    )
    _, bb = mser.detectRegions(gray)
    if len(bb) == 0:
        return np.zeros((0, 4)), np.zeros(0)
    bb = np.asarray(bb, np.float64).reshape(-1, 4) / scale
    boxes = np.column_stack([bb[:, 0], bb[:, 1], bb[:, 0] + bb[:, 2], bb[:, 1] + bb[:, 3]])
    boxes = np.clip(boxes, 0, [w, h, w, h])
    frac = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]) / (w * h)
    ok = (frac >= cfg.min_area_frac) & (frac <= cfg.max_area_frac)
    boxes, frac = np.round(boxes[ok], 2), frac[ok]
    boxes, idx = np.unique(boxes, axis=0, return_index=True)
    frac = frac[idx]
    keep = nms(boxes, frac, cfg.nms_iou)[: cfg.max_boxes]
    return boxes[keep], frac[keep]


def segment_boxes(rgb: np.ndarray, cfg: SegmentsConfig) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of colour regions in full-image pixels, scored by their area fraction; (k, 4), (k,).

    The pixels of a copy ``work_width`` wide (CIELAB, lightly blurred) fall into ``cfg.k`` colour
    clusters by faiss k-means (seeded); each cluster's mask, closed with each kernel of
    ``cfg.closings`` so that the cells of a textured object merge, gives the bounding boxes of its
    8-connected regions (``cv2.connectedComponentsWithStats``). A new object of its own colours
    is a region of its own, whatever the edges of the scene around it.
    """
    import faiss

    h, w = rgb.shape[:2]
    small, scale = _working_copy(rgb, cfg.work_width)
    lab = cv2.cvtColor(cv2.GaussianBlur(small, (0, 0), 0.8), cv2.COLOR_RGB2Lab)
    px = np.ascontiguousarray(lab.reshape(-1, 3), np.float32)
    k = max(1, min(cfg.k, len(px) // 39))  # faiss wants 39 points per centroid
    km = faiss.Kmeans(3, k, niter=20, seed=cfg.seed, verbose=False)
    km.train(px)
    labels = km.index.search(px, 1)[1].reshape(lab.shape[:2])
    area = float(lab.shape[0] * lab.shape[1])
    found = []
    for c in range(k):
        mask = (labels == c).astype(np.uint8)
        for size in cfg.closings:
            m = (
                mask
                if size <= 1
                else cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((size, size), np.uint8))
            )
            n, _, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
            found.append(stats[1:n, :4])
    bb = np.unique(np.concatenate(found).astype(np.float64).reshape(-1, 4), axis=0)
    frac = bb[:, 2] * bb[:, 3] / area
    bb = bb[(frac >= cfg.min_area_frac) & (frac <= cfg.max_area_frac)]
    if not len(bb):
        return np.zeros((0, 4)), np.zeros(0)
    boxes = np.column_stack([bb[:, 0], bb[:, 1], bb[:, 0] + bb[:, 2], bb[:, 1] + bb[:, 3]])
    boxes = np.clip(np.round(boxes / scale, 2), 0, [w, h, w, h])
    frac = bb[:, 2] * bb[:, 3] / area
    keep = nms(boxes, frac, cfg.nms_iou)[: cfg.max_boxes]
    return boxes[keep], frac[keep]


def edge_boxes(rgb: np.ndarray, cfg: EdgesConfig) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of closed edge contours at several dilation scales, scored by edge density.

    Returns boxes (k, 4) and scores (k,).

    Canny thresholds follow the image's median grey level; each dilation size merges nearby
    edges into larger contours, so one image gives parts and whole objects alike.
    """
    h, w = rgb.shape[:2]
    small, scale = _working_copy(rgb, cfg.work_width)
    gray = cv2.GaussianBlur(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), (0, 0), 1.0)
    med = float(np.median(gray))
    edges = cv2.Canny(gray, int(0.33 * med), int(0.66 * med) + 1)
    found = []
    for k in cfg.dilations:
        d = cv2.dilate(edges, np.ones((k, k), np.uint8)) if k > 1 else edges
        contours, _ = cv2.findContours(d, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        found += [cv2.boundingRect(c) for c in contours]
    if not found:
        return np.zeros((0, 4)), np.zeros(0)
    bb = np.unique(np.asarray(found, np.int64).reshape(-1, 4), axis=0)
    x1, y1, x2, y2 = bb[:, 0], bb[:, 1], bb[:, 0] + bb[:, 2], bb[:, 1] + bb[:, 3]
    frac = (x2 - x1) * (y2 - y1) / float(gray.shape[0] * gray.shape[1])
    ok = (frac >= cfg.min_area_frac) & (frac <= cfg.max_area_frac)
    x1, y1, x2, y2 = x1[ok], y1[ok], x2[ok], y2[ok]
    if not len(x1):
        return np.zeros((0, 4)), np.zeros(0)
    ii = cv2.integral((edges > 0).astype(np.uint8)).astype(np.float64)
    density = (ii[y2, x2] - ii[y1, x2] - ii[y2, x1] + ii[y1, x1]) / ((x2 - x1) * (y2 - y1))
    boxes = np.clip(np.column_stack([x1, y1, x2, y2]) / scale, 0, [w, h, w, h]).astype(np.float64)
    keep = nms(boxes, density, cfg.nms_iou)[: cfg.max_boxes]
    return boxes[keep], density[keep]


# ---------------------------------------------------------------- YOLO (TorchScript)


class YoloProposer:
    """A YOLO-family detector exported to TorchScript or ONNX (``yolo export format=onnx``).

    A ``.onnx`` file runs through OpenCV's ``cv2.dnn`` (no new runtime), any other file through
    ``torch.jit.load``. The model maps a float ``(B, 3, S, S)`` RGB batch in [0, 1] to either
    ``(B, 4 + nc, N)`` (YOLOv8/11 layout: cx, cy, w, h, class scores) or ``(B, N, 5 + nc)``
    (YOLOv5 layout: cx, cy, w, h, objectness, class scores), in input pixels.
    Images are letterboxed to S.
    """

    def __init__(self, cfg: YoloConfig) -> None:
        import torch

        if not cfg.weights:
            raise ConfigError(
                "[proposals.yolo] weights is not set: export a model to TorchScript on a "
                "machine with "
                "ultralytics (yolo export model=yolov8n.pt format=torchscript) and give its "
                "local path"
            )
        path = Path(cfg.weights).expanduser()
        if not path.exists():
            raise ConfigError(
                f"YOLO weights file {path} does not exist; nothing is downloaded at run "
                "time. Export one with "
                "'yolo export model=yolov8n.pt format=torchscript' where ultralytics is "
                "installed and copy the "
                ".torchscript file here"
            )
        self.cfg = cfg
        self.onnx: Any = None
        if path.suffix.lower() == ".onnx":
            try:
                self.onnx = cv2.dnn.readNetFromONNX(str(path))
            except cv2.error as err:
                raise ConfigError(
                    f"{path}: not an ONNX model OpenCV can read: {str(err).strip()[-200:]}"
                ) from None
            return
        dev = cfg.device
        self.device = torch.device(
            "cuda"
            if dev == "auto" and torch.cuda.is_available()
            else ("cpu" if dev == "auto" else dev)
        )
        try:
            self.model = torch.jit.load(str(path), map_location=self.device).eval()
        except (RuntimeError, ValueError) as err:
            raise ConfigError(f"{path}: not a TorchScript model: {err}") from None

    def _letterbox(self, rgb: np.ndarray) -> tuple[np.ndarray, float, tuple[float, float]]:
        s = self.cfg.imgsz
        h, w = rgb.shape[:2]
        r = min(s / h, s / w)
        nw, nh = round(w * r), round(h * r)
        out = np.full((s, s, 3), 114, np.uint8)
        px, py = (s - nw) // 2, (s - nh) // 2
        out[py : py + nh, px : px + nw] = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_LINEAR)
        return out, r, (px, py)

    def __call__(self, images: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Boxes, scores and class ids for each image (boxes in the image's pixels)."""
        import torch

        results = []
        if self.onnx is not None:  # cv2.dnn: one image at a time (exports often fix the batch)
            for im in images:
                box, r, (px, py) = self._letterbox(im)
                blob = np.ascontiguousarray(box.transpose(2, 0, 1)[None], np.float32) / 255.0
                self.onnx.setInput(blob)
                y = np.asarray(self.onnx.forward(), np.float32)
                results.append(self._decode(y[0], r, px, py, im.shape[1], im.shape[0]))
            return results
        for i in range(0, len(images), self.cfg.batch):
            chunk = images[i : i + self.cfg.batch]
            lb = [self._letterbox(im) for im in chunk]
            x = (
                torch.from_numpy(np.stack([b[0] for b in lb]))
                .to(self.device)
                .permute(0, 3, 1, 2)
                .float()
                / 255.0
            )
            with torch.inference_mode():
                y = self.model(x)
            if isinstance(y, (list, tuple)):
                y = y[0]
            y = y.float().cpu().numpy()
            for pred, (_, r, (px, py)), im in zip(y, lb, chunk, strict=True):
                results.append(self._decode(pred, r, px, py, im.shape[1], im.shape[0]))
        return results

    def _decode(
        self, pred: np.ndarray, r: float, px: float, py: float, w: int, h: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if pred.shape[0] < pred.shape[1]:  # (4 + nc, N): v8 layout
            pred = pred.T
            xywh, cls_scores = pred[:, :4], pred[:, 4:]
        else:  # (N, 5 + nc): v5 layout
            xywh, cls_scores = pred[:, :4], pred[:, 5:] * pred[:, 4:5]
        if cls_scores.shape[1] == 0:
            return np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)
        cls = cls_scores.argmax(1)
        score = cls_scores[np.arange(len(cls)), cls]
        ok = score >= self.cfg.conf
        xywh, score, cls = xywh[ok], score[ok], cls[ok]
        boxes = np.column_stack(
            [
                xywh[:, 0] - xywh[:, 2] / 2,
                xywh[:, 1] - xywh[:, 3] / 2,
                xywh[:, 0] + xywh[:, 2] / 2,
                xywh[:, 1] + xywh[:, 3] / 2,
            ]
        )
        boxes = (boxes - [px, py, px, py]) / r
        boxes = np.clip(boxes, 0, [w, h, w, h]).astype(np.float64)
        area_ok = (boxes[:, 2] - boxes[:, 0] >= 1) & (boxes[:, 3] - boxes[:, 1] >= 1)
        boxes, score, cls = boxes[area_ok], score[area_ok], cls[area_ok]
        keep = nms(boxes, score, self.cfg.iou, cls)[: self.cfg.max_det]
        return boxes[keep], score[keep].astype(np.float64), cls[keep].astype(np.int64)


# ---------------------------------------------------------------- user table


def load_file_proposals(path: Path, frames: pd.DataFrame) -> pd.DataFrame:
    """A user's proposal table (CSV or parquet).

    Columns ``session, camera, utime, x1, y1, x2, y2`` [, ``score``, ``class``].

    Raises:
        AnnotationError: naming the row: unknown frame, box of zero area or outside the image.
    """
    path = Path(path)
    if not path.exists():
        raise AnnotationError(f"{path}: proposal file not found")
    df = (
        pd.read_parquet(path)
        if path.suffix == ".parquet"
        else pd.read_csv(path, dtype={"session": str, "camera": str})
    )
    need = ["session", "camera", "utime", "x1", "y1", "x2", "y2"]
    miss = [c for c in need if c not in df.columns]
    if miss:
        raise AnnotationError(f"{path}: missing column(s) {miss}; expected {need} [+ score, class]")
    df = df.reset_index(drop=True)
    df["score"] = df["score"].astype(float) if "score" in df.columns else 1.0
    df["class"] = df["class"].astype(str) if "class" in df.columns else ""
    keys = FRAME_KEY
    m = df.merge(frames[keys + ["width", "height"]].drop_duplicates(keys), on=keys, how="left")
    b = df[["x1", "y1", "x2", "y2"]].to_numpy(np.float64)
    checks = [
        (m["width"].isna().to_numpy(), "unknown frame"),
        (~np.isfinite(b).all(1), "non-numeric box"),
        ((b[:, 2] <= b[:, 0]) | (b[:, 3] <= b[:, 1]), "box has zero or negative area"),
        (
            (b[:, 0] < 0)
            | (b[:, 1] < 0)
            | (b[:, 2] > m["width"].to_numpy())
            | (b[:, 3] > m["height"].to_numpy()),
            "box outside the image",
        ),
    ]
    for mask, what in checks:
        mask = np.asarray(mask, bool)
        if mask.any():
            i = int(np.nonzero(mask)[0][0])
            raise AnnotationError(f"{path}: row {i + 1}: {what} ({int(mask.sum())} row(s) in all)")
    return df


# ---------------------------------------------------------------- driver


#: A per-image proposer: the upright (H, W, 3) uint8 RGB image and ``[proposals]`` ->
#: (boxes (k, 4) x1, y1, x2, y2 in pixels, scores (k,), higher = better).
ImageProposer = Callable[[np.ndarray, ProposalsConfig], tuple[np.ndarray, np.ndarray]]


def _edges(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    return edge_boxes(rgb, cfg.edges)


def _mser(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    return mser_boxes(rgb, cfg.mser)


def _segments(rgb: np.ndarray, cfg: ProposalsConfig) -> tuple[np.ndarray, np.ndarray]:
    return segment_boxes(rgb, cfg.segments)


#: Proposal methods that read one image at a time, by name (``[proposals] methods``): the
#: catalogue's registry (``methods.PROPOSERS``), one dict, holding the built-in ones from here on.
IMAGE_METHODS = PROPOSERS
IMAGE_METHODS.update({"edges": _edges, "mser": _mser, "segments": _segments})


def register_method(name: str, proposer: ImageProposer, options: type | None = None) -> None:
    """Add a per-image proposal method, selected by ``name`` in ``[proposals] methods``.

    Its source is part of the proposals' cache key (:func:`method_fingerprints`), so editing it
    recomputes them. Each method gets its own rank engine (SPEC section 6). ``options``, a
    dataclass, is its ``[proposals.<name>]`` table (unknown keys and wrong types rejected at load,
    part of the proposals' key); the proposer reads it as ``cfg.options_of(name)``. Register
    before the config loads.

    Raises:
        ValueError: ``name`` is taken, or ``options`` is not a dataclass.
    """
    fields = [f.name for f in dataclasses.fields(ProposalsConfig)]  # [proposals]'s own keys
    taken = (*SPECIAL_METHODS, *IMAGE_METHODS, *fields)
    if name in taken:
        raise ValueError(f"proposal method {name!r} exists; known: {list(known_methods())}")
    if options is not None and not dataclasses.is_dataclass(options):
        raise ValueError(f"proposal method {name!r}: options must be a dataclass")
    IMAGE_METHODS[name] = proposer
    if options is not None:
        PROPOSER_OPTIONS[name] = options


known_methods = known_proposal_methods


def method_fingerprints(methods: Sequence[str]) -> dict[str, str]:
    """The source hash of each listed method registered from outside the package."""
    return source_fingerprints(IMAGE_METHODS, methods)


def _checked(proposer: str, frame: Any, boxes: Any, scores: Any) -> tuple[np.ndarray, np.ndarray]:
    """A proposer's output as float64 (k, 4) boxes and (k,) scores, or an error naming both.

    Raises:
        ConfigError: The shapes do not match or a value is not finite.
    """
    b, s = np.asarray(boxes, np.float64), np.asarray(scores, np.float64)
    if b.ndim != 2 or b.shape[1] != 4 or s.shape != (len(b),) or not np.isfinite(b).all():
        raise ConfigError(
            f"proposal method {proposer!r} on frame {frame.session}/{frame.camera}/{frame.utime}: "
            f"expected finite boxes (k, 4) and scores (k,), got {b.shape} and {s.shape}"
        )
    return b, s


def _rows(
    f: Any, proposer: str, boxes: np.ndarray, scores: np.ndarray, classes: list[str]
) -> pd.DataFrame:
    """Proposal rows of one frame ``f`` and method (PROPOSAL_COLUMNS)."""
    n = len(boxes)
    return pd.DataFrame(
        {
            "session": f.session,
            "camera": f.camera,
            "utime": np.full(n, f.utime, np.int64),
            "proposal_method": proposer,
            "box_id": np.arange(n, dtype=np.int32),
            "x1": boxes[:, 0] if n else [],
            "y1": boxes[:, 1] if n else [],
            "x2": boxes[:, 2] if n else [],
            "y2": boxes[:, 3] if n else [],
            "score": scores,
            "class": classes,
        }
    )


#: The per-image methods that may read a reduced decode: each works on a copy ``work_width`` wide
#: and gives the same boxes from it (``tests/proposals/test_proposals.py``).
REDUCIBLE = ("edges", "mser")


def decode_scale(width: int, cfg: ProposalsConfig, per_image: Sequence[str], yolo: bool) -> int:
    """The reduced scale (1, 2, 4 or 8) to decode a frame ``width`` pixels wide (upright) at.

    The largest whose width still holds the widest ``work_width`` of the listed OpenCV methods
    (each works on a copy that wide, so it sees the same detail); 1 where ``reduced_decode`` is
    off, YOLO or ``segments`` is listed (measured: its colour clusters move with the decode's
    noise) or a registered method reads the image (their sizes are their own).
    """
    if not cfg.reduced_decode or yolo or any(m not in REDUCIBLE for m in per_image):
        return 1
    need = max((getattr(cfg, m).work_width for m in per_image), default=width)
    return max((k for k in (1, 2, 4, 8) if -(-int(width) // k) >= need), default=1)


def _full_size(boxes: np.ndarray, f: Any, im: np.ndarray) -> np.ndarray:
    """``boxes`` found on ``im`` (a reduced decode of frame ``f``) in the frame's own pixels."""
    h, w = im.shape[:2]
    if (w, h) == (int(f.width), int(f.height)):
        return boxes
    sx, sy = int(f.width) / w, int(f.height) / h
    out = np.round(boxes * np.array([sx, sy, sx, sy]), 2)
    return np.clip(out, 0, [f.width, f.height, f.width, f.height])


def _image_proposals(
    frames: pd.DataFrame,
    cfg: ProposalsConfig,
    methods: list[str],
    progress: Callable[[Iterable], Iterable],
) -> list[pd.DataFrame]:
    """The rows of the methods that read the image: OpenCV's, registered ones, YOLO.

    Frame batch by frame batch, each image read once, at the scale :func:`decode_scale` allows.
    """
    out: list[pd.DataFrame] = []
    per_image = [m for m in IMAGE_METHODS if m in methods]
    if per_image or "yolo" in methods:
        yolo = YoloProposer(cfg.yolo) if "yolo" in methods else None
        batch = max(1, cfg.yolo.batch)
        items = list(frames.itertuples(index=False))
        for i in progress(range(0, len(items), batch)):
            chunk = items[i : i + batch]
            imgs = [
                read_image(f.image, decode_scale(f.width, cfg, per_image, yolo is not None))
                for f in chunk
            ]
            for m in per_image:
                for f, im in zip(chunk, imgs, strict=True):
                    try:
                        found = IMAGE_METHODS[m](im, cfg)
                    except cv2.error as err:
                        raise ConfigError(
                            f"proposal method {m!r} on frame {f.session}/{f.camera}/{f.utime}: "
                            f"OpenCV refused it ({str(err).strip().splitlines()[-1][:160]}); "
                            f"check [proposals.{m}]"
                        ) from None
                    b, s = _checked(m, f, *found)
                    out.append(_rows(f, m, _full_size(b, f, im), s, [""] * len(b)))
            if yolo is not None:
                for f, (b, s, c) in zip(chunk, yolo(imgs), strict=True):
                    out.append(_rows(f, "yolo", b, s, [str(int(k)) for k in c]))
    return out


def _file_proposals(frames: pd.DataFrame, cfg: ProposalsConfig) -> pd.DataFrame:
    """The rows of method ``file``: the user's table, numbered per frame in box order."""
    if not cfg.file:
        raise ConfigError("[proposals] method 'file' needs [proposals] file = <path to the table>")
    fp = load_file_proposals(Path(cfg.file), frames)
    fp = fp.merge(frames[FRAME_KEY], on=FRAME_KEY)
    fp = fp.sort_values(["session", "camera", "utime", "x1", "y1", "x2", "y2"]).reset_index(
        drop=True
    )
    fp["proposal_method"] = "file"
    fp["box_id"] = fp.groupby(FRAME_KEY).cumcount().astype(np.int32)
    return fp[PROPOSAL_COLUMNS]


def compute_proposals(
    frames: pd.DataFrame,
    cfg: ProposalsConfig,
    progress: Callable[[Iterable], Iterable] = lambda it: it,
) -> pd.DataFrame:
    """Proposal rows (PROPOSAL_COLUMNS) of every method in ``cfg.methods`` for every frame."""
    frames = frames.sort_values(FRAME_KEY).reset_index(drop=True)
    out: list[pd.DataFrame] = []
    methods = list(cfg.methods)
    unknown = [m for m in methods if m not in known_methods()]
    if unknown:
        raise ConfigError(
            f"[proposals] unknown method(s) {unknown}; known: {list(known_methods())}"
        )

    if "grid5" in methods:
        for f in frames.itertuples(index=False):
            out.append(_rows(f, "grid5", grid5(f.width, f.height), np.ones(5), [""] * 5))
    out += _image_proposals(frames, cfg, methods, progress)
    if "file" in methods:
        out.append(_file_proposals(frames, cfg))
    df = (
        pd.concat([d for d in out if len(d)], ignore_index=True)
        if out
        else pd.DataFrame(columns=PROPOSAL_COLUMNS)
    )
    df["class"] = df["class"].astype(str)
    return (
        df[PROPOSAL_COLUMNS]
        .sort_values(["proposal_method", "session", "camera", "utime", "box_id"])
        .reset_index(drop=True)
    )


def write_proposals(frames: pd.DataFrame, cfg: ProposalsConfig, name: str, tmp: Path) -> dict:
    """One session's proposals (:func:`compute_proposals`) into ``tmp/proposals.parquet``.

    Args:
        frames: The session's frames.
        cfg: ``[proposals]``.
        name: The session (for the progress bar).
        tmp: The entry's directory.

    Returns:
        ``{"rows": proposal rows, "per_method": rows per method}``.
    """
    df = compute_proposals(
        frames, cfg, progress=partial(progress, desc=f"proposals {name}", unit="batch")
    )
    counts = df.groupby("proposal_method").size()
    empty = [m for m in cfg.methods if len(frames) and int(counts.get(m, 0)) == 0]
    if empty:
        raise HarnessError(
            f"proposals ({name}): method {empty[0]!r} gives no box on any of the session's "
            f"{len(frames)} frames, so 'all proposals' would silently mean the other methods "
            f"alone; change [proposals.{empty[0]}] or remove it from [proposals] methods"
        )
    write_parquet(tmp / "proposals.parquet", df)
    return {"rows": len(df), "per_method": df.groupby("proposal_method").size().to_dict()}

"""The proposals stage's config: ``[proposals]``, its methods' tables (method §5), checks."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

from harness.checks import check_device, check_range, check_value
from harness.methods import PROPOSER_OPTIONS, PROPOSERS, known_proposal_methods


@dataclass(frozen=True)
class YoloConfig:
    """``[proposals.yolo]``: the supervised proposer (a local TorchScript weights file)."""

    # an exported model: .onnx (OpenCV's dnn) or .torchscript (torch); never downloaded
    weights: str | None = None
    # the least confidence of a kept box
    conf: float = 0.05
    # the NMS IoU
    iou: float = 0.7
    # the model's input side, pixels
    imgsz: int = 640
    # frames a call
    batch: int = 8
    # auto, cpu or cuda
    device: str = "auto"
    # boxes a frame at most
    max_det: int = 100


@dataclass(frozen=True)
class MserConfig:
    """``[proposals.mser]``: MSER region proposals (areas as fractions of the image)."""

    # boxes a frame at most
    max_boxes: int = 12
    # the smallest box, a share of the frame's area
    min_area_frac: float = 0.01
    # the largest box, a share of the frame's area
    max_area_frac: float = 0.4
    # the NMS IoU among the boxes
    nms_iou: float = 0.5
    # the working copy's width, pixels
    work_width: int = 320


@dataclass(frozen=True)
class SegmentsConfig:
    """``[proposals.segments]``: colour-region proposals (areas as fractions of the image).

    The frame's pixels (CIELAB, on a copy ``work_width`` wide) fall into ``k`` colour clusters
    (faiss k-means, ``seed``); each cluster's mask is closed with each square kernel of
    ``closings`` (1: as is) so that the cells of a textured object merge; every 8-connected region
    gives its bounding box.
    """

    # colour clusters (k-means)
    k: int = 8
    # morphological closings, pixels, each a set of regions
    closings: tuple[int, ...] = (1, 3, 5)
    # the smallest box, a share of the frame's area
    min_area_frac: float = 0.002
    # the largest box, a share of the frame's area
    max_area_frac: float = 0.5
    # boxes a frame at most
    max_boxes: int = 200
    # the NMS IoU among the boxes
    nms_iou: float = 0.9
    # the working copy's width, pixels
    work_width: int = 320
    # the clustering's (or ranking's) draws
    seed: int = 0


@dataclass(frozen=True)
class SelectiveConfig:
    """``[proposals.selective]``: Selective Search (OpenCV's ``ximgproc``; areas as fractions).

    Uijlings et al.'s hierarchical grouping of a graph segmentation, on a copy ``work_width``
    wide: ``mode`` "fast" (its colour spaces and strategies of the fast mode) or "quality"; the
    first ``max_boxes`` of its boxes within the area limits, near-duplicates (IoU above
    ``nms_iou``) merged. A box's score is its place in Selective Search's order (first: 1). That
    order multiplies each region's level by a random number (the C library's ``rand()``, seeded
    with ``seed`` before every frame, so the boxes are the same on every run).
    """

    # fast or quality (OpenCV's Selective Search modes)
    mode: str = "fast"
    # boxes a frame at most
    max_boxes: int = 300
    # the smallest box, a share of the frame's area
    min_area_frac: float = 0.002
    # the largest box, a share of the frame's area
    max_area_frac: float = 0.5
    # the NMS IoU among the boxes
    nms_iou: float = 0.9
    # the working copy's width, pixels
    work_width: int = 192
    # the clustering's (or ranking's) draws
    seed: int = 0


@dataclass(frozen=True)
class EdgesConfig:
    """``[proposals.edges]``: edge-contour proposals (areas as fractions of the image)."""

    # boxes a frame at most
    max_boxes: int = 12
    # the smallest box, a share of the frame's area
    min_area_frac: float = 0.005
    # the largest box, a share of the frame's area
    max_area_frac: float = 0.4
    # the NMS IoU among the boxes
    nms_iou: float = 0.5
    # the working copy's width, pixels
    work_width: int = 480
    # the edge map's dilations, pixels
    dilations: tuple[int, ...] = (3, 5, 9)


@dataclass(frozen=True)
class ProposalsConfig:
    """``[proposals]``: the proposal methods (method §5) and their sections."""

    # the proposal methods: grid5, edges, full, mser, segments, selective, yolo, file (a plugin's
    # too)
    methods: tuple[str, ...] = ("grid5", "edges")
    # [proposals.edges]
    edges: EdgesConfig = field(default_factory=EdgesConfig)
    # [proposals.yolo]
    yolo: YoloConfig = field(default_factory=YoloConfig)
    # [proposals.mser]
    mser: MserConfig = field(default_factory=MserConfig)
    # [proposals.segments]
    segments: SegmentsConfig = field(default_factory=SegmentsConfig)
    # [proposals.selective]
    selective: SelectiveConfig = field(default_factory=SelectiveConfig)
    # method file: a CSV of boxes per frame (session, camera, utime, x1, y1, x2, y2)
    file: str | None = None
    # decode a JPEG at 1/2, 1/4 or 1/8 of its size where every listed OpenCV method's work_width
    # still fits (libjpeg's DCT scaling: less work than the full frame); false: the full frame
    reduced_decode: bool = True
    # frames read and proposed side by side: edges and mser in threads (OpenCV releases the GIL;
    # both are functions of the image alone), selective in as many worker processes (each seeded
    # per frame); 0: one per core this process may use, 1: one frame at a time. The same boxes
    # whatever the number; other methods run one frame at a time
    threads: int = 0
    # a registered method's [proposals.<name>] table, built as its options dataclass
    options: dict[str, Any] = field(default_factory=dict)

    def options_of(self, proposer: str) -> Any:
        """A registered method's options: its ``[proposals.<method>]`` table, or the defaults.

        Raises:
            KeyError: ``proposer`` was registered without options.
        """
        return self.options[proposer] if proposer in self.options else PROPOSER_OPTIONS[proposer]()


def check_proposals(pr: ProposalsConfig, where: str) -> None:
    """``[proposals]``: known methods, the files they need, each method's options."""
    c = check_value
    known_methods = known_proposal_methods  # the registry (built-ins and registered methods)

    badp = [m for m in pr.methods if m not in known_methods()]
    c(
        not badp and len(pr.methods) > 0,
        where,
        "[proposals] methods",
        list(pr.methods),
        f"a non-empty list of {list(known_methods())}",
    )
    for proposer in pr.methods:  # what each listed method needs of the section (its record)
        for key, attr, allowed in PROPOSERS[proposer].requires:
            value = functools.reduce(getattr, attr.split("."), pr)
            c(bool(value), where, key, value, allowed)
    c(pr.threads >= 0, where, "[proposals] threads", pr.threads, ">= 0 (0: automatic)")
    c(0 <= pr.yolo.conf <= 1, where, "[proposals.yolo] conf", pr.yolo.conf, "[0, 1]")
    c(0 < pr.yolo.iou <= 1, where, "[proposals.yolo] iou", pr.yolo.iou, "(0, 1]")
    for key in ("imgsz", "batch", "max_det"):
        c(
            getattr(pr.yolo, key) >= 1,
            where,
            f"[proposals.yolo] {key}",
            getattr(pr.yolo, key),
            ">= 1",
        )
    c(
        pr.yolo.imgsz % 32 == 0,
        where,
        "[proposals.yolo] imgsz",
        pr.yolo.imgsz,
        "a multiple of 32 (YOLO strides)",
    )
    check_device(pr.yolo.device, where, "[proposals.yolo] device")
    c(
        all(d >= 1 and d % 2 == 1 for d in pr.edges.dilations) and len(pr.edges.dilations) > 0,
        where,
        "[proposals.edges] dilations",
        list(pr.edges.dilations),
        "a non-empty list of odd kernel sizes >= 1",
    )
    seg = pr.segments
    c(2 <= seg.k <= 64, where, "[proposals.segments] k", seg.k, "a colour cluster count in [2, 64]")
    c(
        all(d >= 1 for d in seg.closings) and len(seg.closings) > 0,
        where,
        "[proposals.segments] closings",
        list(seg.closings),
        "a non-empty list of kernel sizes >= 1",
    )
    c(
        pr.selective.mode in ("fast", "quality"),
        where,
        "[proposals.selective] mode",
        pr.selective.mode,
        "fast or quality",
    )
    for sub_name in ("edges", "mser", "segments", "selective"):
        sub = getattr(pr, sub_name)
        c(sub.max_boxes >= 1, where, f"[proposals.{sub_name}] max_boxes", sub.max_boxes, ">= 1")
        c(0 < sub.nms_iou <= 1, where, f"[proposals.{sub_name}] nms_iou", sub.nms_iou, "(0, 1]")
        c(
            sub.work_width >= 16,
            where,
            f"[proposals.{sub_name}] work_width",
            sub.work_width,
            ">= 16 pixels",
        )
        check_range(
            where,
            f"[proposals.{sub_name}] min_area_frac..max_area_frac",
            (sub.min_area_frac, sub.max_area_frac),
        )

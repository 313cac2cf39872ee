"""The configuration's schema: one frozen dataclass per stage and the run's localizers.

Loaded and checked by :mod:`harness.config.load` (TOML, unknown keys rejected) and
:mod:`harness.config.check` (ranges, at load time).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from harness.methods import ALL_METHODS, PROPOSER_OPTIONS
from harness.records import season_of

#: A localizer's name: it heads tables and names files (never a path).
LOCALIZER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,63}")
#: What a name that is not one is told (``[[localizers]]`` and ``--import`` alike).
LOCALIZER_NAME_RULE = (
    "1-64 ASCII letters, digits, '.', '_', '-' or '+', starting with a letter or digit"
)


def is_localizer_name(name: object) -> bool:
    """Whether ``name`` may name a localizer: one check for ``[[localizers]]`` and ``--import``."""
    return isinstance(name, str) and LOCALIZER_NAME.fullmatch(name) is not None


#: ``[descriptor] precision``: the encoder's arithmetic (``auto``: bf16 where native).
PRECISIONS = ("auto", "fp32", "bf16")
#: The name of the cross-localizer block (SPEC section 11).
ALL_LOCALIZERS = "all localizers"


@dataclass(frozen=True)
class SessionConfig:
    """One season log.

    ``source`` is an NCLT root, a ``.bag``, a ROS2 bag directory or an ``.mcap``.
    """

    name: str
    source: str
    season: str = ""
    format: str = "auto"
    camera: str = "Cam5"
    image_topic: str | None = None
    pose_topic: str | None = None
    tf_child_frame: str | None = None  # older name of camera_frame: the frame whose pose /tf gives
    # /tf: the frame poses are expressed in (default: the tree's root)
    fixed_frame: str | None = None
    # /tf: the camera's frame (default: the images' header.frame_id)
    camera_frame: str | None = None


@dataclass(frozen=True)
class IngestConfig:
    """``[ingest]``: how logs become frames (times in seconds)."""

    # the largest image a header may declare (width x height): larger is a decompression bomb
    max_image_pixels: int = 100_000_000
    # pose topics and fast /tf transforms: a sample at most this before and after an image
    max_pose_gap_s: float = 0.1
    # /tf transforms published more slowly than max_pose_gap_s (map -> odom at 1-10 Hz)
    max_tf_gap_s: float = 1.0
    time_source: str = "header"  # header stamp of the image message, or "log" (bag receive time)
    nclt_rotation: str = "cw"  # how NCLT's stored images are turned upright: cw, ccw, none
    salvage: bool = False  # keep the messages read before a truncated or corrupt part
    # lossless image store for raw images from logs: tiff (fast) or png (smaller)
    store_format: str = "tiff"
    # decode every compressed image in full at ingest; drop and count broken ones
    verify_images: bool = False


#: ``[pairs] by``: how a query frame finds its map frame (SPEC 4 and 13.2).
PAIR_MODES = ("pose", "name", "order", "retrieval", "sequence")


@dataclass(frozen=True)
class PairsConfig:
    """``[pairs]``: cross-season pairing (SPEC section 4; degrees, metres)."""

    max_yaw_diff_deg: float = 45.0
    max_distance_m: float | None = 10.0
    stride_m: float = 0.0
    queries: str = "annotated"  # "annotated": only annotated query frames; "all": every frame
    # "pose": the nearest viewpoint by pose (SPEC 4); sessions without poses (SPEC 13.2):
    # "name": the map image of the same file name (stem); "order": the i-th image of each session
    # in file-name order; "retrieval": the map frame the query's subimages retrieve best with the
    # run's localizer; "sequence": the same retrieval scored over runs of consecutive frames
    # (SeqSLAM), for two traverses of one route
    by: str = "pose"
    # by other than "pose": the ground-truth place is the paired frame and this many neighbours
    # on each side in the map's order (SPEC 13.2)
    place_frames: int = 2
    # a pair whose pair_confidence is below this is an "uncertain pair": flagged in frames.csv,
    # left out of detect's most-changed list and marked on the page (SPEC 13.2)
    min_pair_confidence: float = 0.05
    # by = "sequence": the query frames of one sequence window (centred on the frame)
    sequence_frames: int = 11


@dataclass(frozen=True)
class YoloConfig:
    """``[proposals.yolo]``: the supervised proposer (a local TorchScript weights file)."""

    weights: str | None = None
    conf: float = 0.05
    iou: float = 0.7
    imgsz: int = 640
    batch: int = 8
    device: str = "auto"
    max_det: int = 100


@dataclass(frozen=True)
class MserConfig:
    """``[proposals.mser]``: MSER region proposals (areas as fractions of the image)."""

    max_boxes: int = 12
    min_area_frac: float = 0.01
    max_area_frac: float = 0.4
    nms_iou: float = 0.5
    work_width: int = 320


@dataclass(frozen=True)
class SegmentsConfig:
    """``[proposals.segments]``: colour-region proposals (areas as fractions of the image).

    The frame's pixels (CIELAB, on a copy ``work_width`` wide) fall into ``k`` colour clusters
    (faiss k-means, ``seed``); each cluster's mask is closed with each square kernel of
    ``closings`` (1: as is) so that the cells of a textured object merge; every 8-connected region
    gives its bounding box.
    """

    k: int = 8
    closings: tuple[int, ...] = (1, 3, 5)
    min_area_frac: float = 0.002
    max_area_frac: float = 0.5
    max_boxes: int = 200
    nms_iou: float = 0.9
    work_width: int = 320
    seed: int = 0


@dataclass(frozen=True)
class EdgesConfig:
    """``[proposals.edges]``: edge-contour proposals (areas as fractions of the image)."""

    max_boxes: int = 12
    min_area_frac: float = 0.005
    max_area_frac: float = 0.4
    nms_iou: float = 0.5
    work_width: int = 480
    dilations: tuple[int, ...] = (3, 5, 9)


@dataclass(frozen=True)
class ProposalsConfig:
    """``[proposals]``: the proposal methods (SPEC section 5) and their sections."""

    methods: tuple[str, ...] = ("grid5", "edges")
    edges: EdgesConfig = field(default_factory=EdgesConfig)
    yolo: YoloConfig = field(default_factory=YoloConfig)
    mser: MserConfig = field(default_factory=MserConfig)
    segments: SegmentsConfig = field(default_factory=SegmentsConfig)
    file: str | None = None
    # decode a JPEG at 1/2, 1/4 or 1/8 of its size where every listed OpenCV method's work_width
    # still fits (libjpeg's DCT scaling: less work than the full frame); false: the full frame
    reduced_decode: bool = True
    # a registered method's [proposals.<name>] table, built as its options dataclass
    options: dict[str, Any] = field(default_factory=dict)

    def options_of(self, proposer: str) -> Any:
        """A registered method's options: its ``[proposals.<method>]`` table, or the defaults.

        Raises:
            KeyError: ``proposer`` was registered without options.
        """
        return self.options[proposer] if proposer in self.options else PROPOSER_OPTIONS[proposer]()


@dataclass(frozen=True)
class DescriptorConfig:
    """``[descriptor]``: the subimage descriptor, its training and encoding (SPEC section 6)."""

    name: str = "autoencoder"
    input_size: int = 256
    channels: tuple[int, int, int] = (32, 32, 16)
    input_norm: str = "none"  # "none" (the paper) or "per_crop": standardise each crop's channels
    epochs: int = 4
    batch_size: int = 32  # training batch
    # subimages per encoder call; 0: 2 on CPU (keeps activations in cache), batch_size on GPU
    encode_batch: int = 0
    lr: float = 1e-3
    max_train_subimages: int = 4000
    # > 0: train on this many sample-steps (not epochs) with early stopping on held-out crops
    train_samples: int = 0
    # share of the training crops held out for early stopping (train_samples > 0)
    holdout: float = 0.1
    eval_every: int = 50  # steps between held-out evaluations
    patience: int = 4  # evaluations without improvement before training stops
    dtype: str = "float16"
    device: str = "auto"
    # the encoder's arithmetic, training and inference: "fp32", "bf16" (torch.autocast) or "auto"
    # (bf16 where the device multiplies bf16 natively: AVX512-BF16 or AMX, a CUDA GPU with bf16)
    precision: str = "auto"
    seed: int = 0
    num_workers: int = 0
    # frames per cached descriptor shard (the unit an interrupted run resumes at)
    shard_frames: int = 256
    # name = "torchscript" or "onnx": a user's network from a local file (its content is keyed)
    path: str = ""
    mean: tuple[float, float, float] = (0.485, 0.456, 0.406)  # per RGB channel, values in [0, 1]
    std: tuple[float, float, float] = (0.229, 0.224, 0.225)
    pooling: str = "avg"  # of a (N, C, H, W) output: "avg", "max" or "gem"
    gem_p: float = 3.0
    # "reduced": decode each frame at 1/2, 1/4 or 1/8 where every box keeps input_size pixels
    # (JPEG: libjpeg's scaled decode); "full": always the whole frame
    decode: str = "reduced"
    # batches of crops a reader thread decodes ahead of the encoder (0: none; with num_workers
    # > 0 the loader's processes decode ahead instead). 0 by default: on CPU the encoder already
    # uses every core, and the thread measured no faster (bench case crops); 2 with a GPU encoder
    prefetch: int = 0


@dataclass(frozen=True)
class RetrievalConfig:
    """``[retrieval]``: the rank engine, the ground-truth place and the database (metres)."""

    engine: str = "exact"  # exact or faiss
    # ground-truth place: reference frames within this radius of G (SPEC 6); 0: G alone
    gt_radius_m: float = 2.0
    # reference database by place: one frame per this many metres of trajectory; 0: every frame
    db_stride_m: float = 0.0
    chunk_rows: int = 8192
    query_batch: int = 1024
    # exact engine: budget (MiB) of the (queries x frames) matrices per database pass; bounds memory
    # whatever the data size
    memory_mb: float = 1024.0
    faiss_nlist: int = 0  # 0: flat index; >0: IVF with that many lists
    faiss_nprobe: int = 8
    query_frames_per_shard: int = 512  # pairs per ranking unit (the unit mapped over executors)
    faiss_check: int = 256  # queries per engine also ranked exactly, to report faiss's recall


@dataclass(frozen=True)
class ProjectionConfig:
    """Compact descriptors (docs/method.md).

    PCA or PCA-whitening to ``dim``, fitted on the reference sessions.
    """

    # 0: off, rank with the full descriptor (SPEC 6); > 0: project to this many dimensions
    dim: int = 0
    whiten: bool = False  # divide each component by its standard deviation before re-normalising
    # reference subimages (a seeded sample) encoded to fit the directions; memory fit_samples x D x
    # 4 bytes
    fit_samples: int = 8192
    seed: int = 0


@dataclass(frozen=True)
class FusionConfig:
    """``[fusion]``: the methods of SPEC section 7 that are computed and reported."""

    # computed and reported; SPEC order is kept whatever the order here
    methods: tuple[str, ...] = ALL_METHODS
    seed: int = 0
    max_fused_boxes: int = 4096
    rrf_c: float = 60.0  # RRF's constant c (SPEC section 14; Cormack et al. 2009 use 60)


@dataclass(frozen=True)
class SplitsConfig:
    """``[splits]``: RoC/SoB ranges of the difficulty splits and Table S strata (SPEC 8)."""

    roc_max: tuple[float, ...] = (0.01, 0.02, 0.03, 0.04, 0.05)
    pos_roc: tuple[float, float] = (0.9, 1.0)
    pos_sob: tuple[float, float] = (0.0, 0.4)
    neg_roc_min: float = 0.0
    neg_sob: tuple[float, float] = (0.4, 1.0)
    sob_strata: tuple[float, ...] = (
        0.0,
        0.02,
        0.05,
        0.1,
        0.2,
        0.4,
        1.0,
    )  # Table S: SoB strata edges, [lo, hi), the last closed


@dataclass(frozen=True)
class ReportConfig:
    """``[report]``: bootstrap, plots, ``report.html`` and its gallery."""

    bootstrap: int = 1000
    ci: float = 0.95
    # SPEC 9: random orders of the same samples behind every floor and chance band (>= 200)
    chance_draws: int = 200
    # SPEC 9, evidence before a verdict: a figure whose positives sit in fewer query images than
    # this (or whose bootstrap cannot vary it) prints "too few positives (n)" and no verdict
    min_positive_images: int = 5
    locmap_examples: int = 4
    plots: bool = True
    html: bool = True  # write report.html (the one page to look at) after the tables
    gallery: int = 3  # report.html: worst false positives and missed changes shown per method
    # the RoC-max of the page's figures (PR curves, season pairs, gallery) and of Table L
    headline_roc_max: float = 0.05
    # recall@N of the localization table and Table L, as the VPR benchmarks report it
    recall_at: tuple[int, ...] = (1, 5, 10, 20)
    # > 0: the localization table again with the place this many metres wide (ranks re-ranked
    # with [retrieval] gt_radius_m replaced; nothing else changes); 0: off
    gt_radius_also: float = 0.0


#: The alignment chain's links, in the order they are usually tried.
ALIGNERS = ("homography", "ecc", "identity")
FEATURE_IMAGES = ("gradient", "gray")
KEYPOINTS = ("orb", "sift")


@dataclass(frozen=True)
class LocalConfig:
    """A ``local`` localizer's options (SPEC 13.3, :mod:`harness.localizers.local`).

    ``[[localizers]] local = {...}`` or ``[detect.local]``.
    """

    # the alignment chain, tried in order; a pair none of them accepts is "not aligned"
    align: tuple[str, ...] = ("homography", "identity")
    # the homography's local features: "orb" (measured as good as SIFT here, and cheaper) or "sift"
    keypoints: str = "orb"
    max_keypoints: int = 800
    # a homography is accepted with at least this many RANSAC inliers ...
    min_inliers: int = 12
    # ... and a plausible warp: no frame corner moves more than this share of the frame diagonal
    max_corner_shift: float = 0.35
    # ECC's correlation (enhanced correlation coefficient) at which its affine fit is accepted
    ecc_min_cc: float = 0.6
    # identity is accepted where the two work images correlate at least this much (an overlap)
    identity_min_ncc: float = 0.0
    # the image matched: "gradient" (Sobel magnitude, robust to light and season) or "gray"
    image: str = "gradient"
    # the search window: the box grown by this share of its width / height on each side ...
    grow: float = 0.25
    min_grow_px: int = 4
    # ... and the tolerance around the expected position: this share of the frame's diagonal
    # (what alignment leaves scales with the frame), at least min_tolerance_px ...
    tolerance: float = 0.015
    min_tolerance_px: int = 1
    # ... and the window grows at least this many tolerances on each side
    window_over_tolerance: int = 1
    # also match the map's patch in the query frame and keep the worse rank (removed objects)
    both_directions: bool = True
    # frames whose longer side exceeds this are worked on at 1/2, 1/4 or 1/8 of their size
    work_side: int = 400
    # ... and aligned on a pyramid level whose longer side is at most this
    align_side: int = 320
    # a box whose shorter side exceeds this is matched on a coarser pyramid level (halved until
    # it is not): the resolution the box needs, not more
    max_template_px: int = 32
    # query frames per cached unit (the unit a killed run resumes at); not in the key
    frames_per_unit: int = 64


@dataclass(frozen=True)
class DetectConfig:
    """``[detect]``: how ``harness detect`` turns LoC into change boxes (SPEC 13.1)."""

    # the box generator: "subimages" (the ranked subimages, each scored by its own r: with the
    # local localizer, the frame's colour regions, SPEC 13.3), "fused" (the fused qBBs, SPEC 13),
    # "locmap" (connected regions of the
    # thresholded LoC map), "proposals" (the original proposals scored by the LoC inside) or
    # "segments" (the frame's colour regions, [proposals.segments], scored by the LoC inside)
    boxes: str = "subimages"
    # locmap / proposals / segments: a box's score from the LoC map, "max" or "mean" inside it,
    # or "contrast" (the mean inside less the mean of the ring around it, half the box wide)
    box_score: str = "max"
    # locmap: the level, as a share of the frame's LoC range (lo + level * (hi - lo))
    locmap_level: float = 0.5
    # the narrowest change box, pixels a side: thinner candidates (slivers where fused qBBs
    # barely overlap) are dropped before NMS and counted (detect.json: thin_boxes_dropped)
    min_box_side: float = 2.0
    # the nominal false-alarm rate: boxes and frames whose calibrated score (exceedance) is at
    # most this are alarms (alarms.csv; harness detect --alarm overrides it)
    alarm: float = 0.01
    # what ranks the subimages: "local" (each subimage of the frame's colour regions ranked inside
    # its paired map frame, SPEC 13.3, with [detect.local]) or "config" (the config's localizers)
    localizer: str = "local"
    # a prior a box's score is fused with: "area" (the mean of the box's percentile among its
    # frame's candidates by score and by area, SPEC 13.3: docs/method.md measures it) or "none"
    box_prior: str = "area"
    # the local localizer's options (harness.localizers.local.LocalConfig)
    local: LocalConfig = field(default_factory=LocalConfig)


@dataclass(frozen=True)
class FixtureConfig:
    """Generate the fixture into ``data_root`` when it is absent."""

    generate: bool = False
    seed: int = 0
    frames: int = 64
    width: int = 120
    height: int = 160
    objects: int = 9
    loop_scale: float = 1.5
    render_scale: int = 1  # ray-cast at 1/scale resolution and upsample (NCLT-sized frames cheaply)
    formats: tuple[str, ...] = ()  # log format per session; empty: nclt, ros1, ros2, mcap


@dataclass(frozen=True)
class ImportConfig:
    """``[import]``: how an imported localizer's rank file is read (SPEC section 12)."""

    # what a row's ``scores`` are: "distance" (smaller = more similar) or "similarity" in [0, 1]
    score_kind: str = "distance"
    # a query image of the pairs without any imported row: an error (false), or left out of
    # every table and counted (true)
    allow_unranked_images: bool = False


@dataclass(frozen=True)
class BovwConfig:
    """A bag-of-visual-words localizer (SPEC section 11): local features, words, TF-IDF, L1.

    Each subimage is resized to ``input_size`` x ``input_size`` (as the autoencoder's input);
    features are ``sift``, ``rootsift`` or ``orb`` at a dense grid of keypoints (``dense``: every
    ``step`` pixels, diameter ``patch``) or at the detector's own keypoints. ``k`` words are
    learned with faiss k-means on at most ``max_train_features`` features of reference-session
    subimages; IDF from the same subimages.
    """

    features: str = "rootsift"
    k: int = 1024
    dense: bool = True
    step: int = 8
    patch: int = 16
    input_size: int = 128
    max_train_subimages: int = 4000
    max_train_features: int = 200_000
    kmeans_iter: int = 20
    seed: int = 0
    num_workers: int = 0
    # frames per cached encoding shard (the unit an interrupted run resumes at)
    shard_frames: int = 256
    # batches of crops a reader thread decodes ahead of the feature extraction (0: none); the
    # features use one core, the thread another (bench case crops: 1.10x)
    prefetch: int = 2


@dataclass(frozen=True)
class LocalizerImportConfig:
    """A localizer's ``import`` table: ranked lists from a file (SPEC section 12)."""

    file: str
    score_kind: str = "distance"


@dataclass(frozen=True)
class LocalizerConfig:
    """One ``[[localizers]]`` entry (SPEC section 11): a name, proposals and one way to rank.

    ``kind`` names a :data:`harness.config.kinds.LOCALIZER_KINDS` record and ``options`` is its
    sub-table (a ``DescriptorConfig``, ``BovwConfig``, ``LocalizerImportConfig`` or a registered
    kind's dataclass); ``proposals`` are the ``[proposals] methods`` it uses (all by default).
    """

    name: str
    kind: str
    proposals: tuple[str, ...]
    options: Any = None

    @property
    def descriptor(self) -> DescriptorConfig | None:
        """The options of a ``descriptor`` localizer, else None."""
        return self.options if self.kind == "descriptor" else None

    @property
    def bovw(self) -> BovwConfig | None:
        """The options of a ``bovw`` localizer, else None."""
        return self.options if self.kind == "bovw" else None

    @property
    def import_(self) -> LocalizerImportConfig | None:
        """The options of an ``import`` localizer, else None."""
        return self.options if self.kind == "import" else None


@dataclass(frozen=True)
class MasksConfig:
    """``[masks]``: change masks as annotations (SPEC 13.2).

    ``folder``: one 0/255 image per annotated image of a folder session, named like it; its
    8-connected components of at least ``min_mask_area`` pixels are change boxes, an all-zero
    mask a no-change image.
    """

    folder: str | None = None
    min_mask_area: int = 16


@dataclass(frozen=True)
class Config:
    """A whole run's configuration, as loaded from TOML and checked (:func:`load_config`)."""

    name: str
    data_root: Path
    annotations: Path | None  # None: no annotation file (harness detect only)
    sessions: tuple[SessionConfig, ...]
    seed: int = 0
    ingest: IngestConfig = field(default_factory=IngestConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    proposals: ProposalsConfig = field(default_factory=ProposalsConfig)
    descriptor: DescriptorConfig = field(default_factory=DescriptorConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    splits: SplitsConfig = field(default_factory=SplitsConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    masks: MasksConfig = field(default_factory=MasksConfig)
    fixture: FixtureConfig = field(default_factory=FixtureConfig)
    import_: ImportConfig = field(default_factory=ImportConfig)  # the TOML table [import]
    # [[localizers]]; empty: one localizer named after [descriptor] (:meth:`localizer_set`)
    localizers: tuple[LocalizerConfig, ...] = ()

    def localizer_set(self) -> tuple[LocalizerConfig, ...]:
        """The localizers of the run: ``[[localizers]]``, or the one ``[descriptor]`` defines."""
        if self.localizers:
            return self.localizers
        return (
            LocalizerConfig(
                name=self.descriptor.name,
                kind="descriptor",
                proposals=self.proposals.methods,
                options=self.descriptor,
            ),
        )

    def seasons(self) -> dict[str, str]:
        """Session name -> season code (``WI``, ``SP``, ``SU``, ``AU``)."""
        return {s.name: s.season or season_of(s.name) for s in self.sessions}

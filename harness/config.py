"""Configuration: one frozen dataclass per stage, loaded from TOML with unknown keys rejected.

A config file is a TOML document; ``load_config`` resolves relative paths against the file's
directory's project root (the directory holding ``pyproject.toml`` above it, else the file's
directory) and substitutes ``{data_root}`` in session sources.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from .errors import ConfigError
from .inputs import read_text

# the method catalogue lives in ``methods`` (the bottom of the house); named here too, as before
from .methods import ALL_METHODS as ALL_METHODS
from .methods import BASELINES as BASELINES
from .methods import EXTRA_METHODS as EXTRA_METHODS
from .methods import FUSION_METHODS as FUSION_METHODS
from .methods import known_fusion_methods, known_proposal_methods

T = TypeVar("T")


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


@dataclass(frozen=True)
class PairsConfig:
    """``[pairs]``: cross-season pairing (SPEC section 4; degrees, metres)."""

    max_yaw_diff_deg: float = 45.0
    max_distance_m: float | None = 10.0
    stride_m: float = 0.0
    queries: str = "annotated"  # "annotated": only annotated query frames; "all": every frame


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
    file: str | None = None


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
    locmap_examples: int = 4
    plots: bool = True
    html: bool = True  # write report.html (the one page to look at) after the tables
    gallery: int = 3  # report.html: worst false positives and missed changes shown per method
    # the RoC-max of the page's figures (PR curves, season pairs, gallery) and of Table L
    headline_roc_max: float = 0.05


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


@dataclass(frozen=True)
class LocalizerImportConfig:
    """A localizer's ``import`` table: ranked lists from a file (SPEC section 12)."""

    file: str
    score_kind: str = "distance"


@dataclass(frozen=True)
class LocalizerConfig:
    """One ``[[localizers]]`` entry (SPEC section 11): a name, proposals and one way to rank.

    ``kind`` is ``descriptor`` (with ``descriptor``), ``bovw`` (with ``bovw``) or ``import``
    (with ``import_``); ``proposals`` are the ``[proposals] methods`` it uses (all by default).
    """

    name: str
    kind: str
    proposals: tuple[str, ...]
    descriptor: DescriptorConfig | None = None
    bovw: BovwConfig | None = None
    import_: LocalizerImportConfig | None = None


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
                descriptor=self.descriptor,
            ),
        )

    def seasons(self) -> dict[str, str]:
        """Session name -> season code (``WI``, ``SP``, ``SU``, ``AU``)."""
        from .records import season_of

        return {s.name: s.season or season_of(s.name) for s in self.sessions}


def _type_name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """Check ``value`` (from TOML) against the field's type hint; lists become tuples, ints floats.

    Raises:
        ConfigError: naming the key, the value and the expected type.
    """
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union):
        last: ConfigError | None = None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as err:
                last = err
        raise last or ConfigError(f"{where}: unexpected value {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(
                f"{where}: expected a list of {len(args)} values, got {list(value)!r}"
            )
        return tuple(
            _coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: {value!r} is not a finite number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _build(cls: type[T], data: Any, where: str) -> T:
    """Build dataclass ``cls`` from a dict, rejecting unknown keys and values of the wrong type."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(fields)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        sub = _NESTED.get((cls.__name__, name))
        if sub is not None:
            kwargs[name] = _build(sub, value, f"{where}.{name}")
        else:
            kwargs[name] = _coerce(value, hints[name], f"{where} {name}")
    try:
        return cls(**kwargs)
    except TypeError as err:
        raise ConfigError(f"{where}: {err}") from None


_NESTED: dict[tuple[str, str], type] = {
    ("ProposalsConfig", "yolo"): YoloConfig,
    ("ProposalsConfig", "mser"): MserConfig,
    ("ProposalsConfig", "edges"): EdgesConfig,
}

_SECTIONS: dict[str, type] = {
    "ingest": IngestConfig,
    "pairs": PairsConfig,
    "proposals": ProposalsConfig,
    "descriptor": DescriptorConfig,
    "retrieval": RetrievalConfig,
    "projection": ProjectionConfig,
    "fusion": FusionConfig,
    "splits": SplitsConfig,
    "report": ReportConfig,
    "fixture": FixtureConfig,
    "import": ImportConfig,
}
#: TOML tables whose field name differs (``import`` is a Python keyword).
_FIELD = {"import": "import_"}


def project_root(start: Path) -> Path:
    """The nearest directory at or above ``start`` holding ``pyproject.toml`` (else ``start``)."""
    start = start.resolve()
    for d in (start, *start.parents):
        if (d / "pyproject.toml").exists():
            return d
    return start


def parse_config(
    doc: dict[str, Any], base: Path, where: str, data_root: str | None = None
) -> Config:
    """Build a :class:`Config` from a parsed TOML document.

    Relative paths resolve against ``base``.
    """
    top_keys = {"name", "data_root", "annotations", "sessions", "seed", "localizers", *_SECTIONS}
    unknown = sorted(set(doc) - top_keys)
    if unknown:
        raise ConfigError(f"{where}: unknown top-level key(s) {unknown}; known: {sorted(top_keys)}")
    for required in ("name", "sessions"):
        if required not in doc:
            raise ConfigError(f"{where}: missing required key {required!r}")
    for key in ("name", "annotations", "data_root"):
        if key in doc and (not isinstance(doc[key], str) or not doc[key].strip()):
            raise ConfigError(f"{where}: {key} = {doc[key]!r}: expected a non-empty string")
    seed = doc.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{where}: seed = {seed!r}: expected an integer >= 0")
    root_text = data_root if data_root is not None else str(doc.get("data_root", "."))
    root = Path(root_text).expanduser()
    root = root if root.is_absolute() else (base / root)
    sessions = []
    if not isinstance(doc["sessions"], list) or not doc["sessions"]:
        raise ConfigError(f"{where}: 'sessions' must be a non-empty array of tables")
    for i, s in enumerate(doc["sessions"]):
        sc = _build(SessionConfig, s, f"{where}: sessions[{i}]")
        src = Path(sc.source.replace("{data_root}", str(root))).expanduser()
        src = src if src.is_absolute() else base / src
        sessions.append(dataclasses.replace(sc, source=str(src)))
    for i, sc in enumerate(sessions):
        check_session_name(sc.name, f"{where}: sessions[{i}] name")
        check_session_name(sc.camera, f"{where}: sessions[{i}] camera")
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: session names must be unique, got {names}")
    ann: Path | None = None
    if "annotations" in doc:
        ann = Path(str(doc["annotations"]).replace("{data_root}", str(root))).expanduser()
        ann = ann if ann.is_absolute() else base / ann
    kwargs: dict[str, Any] = {}
    for section, cls in _SECTIONS.items():
        if section in doc:
            kwargs[_FIELD.get(section, section)] = _build(
                cls, doc[section], f"{where}: [{section}]"
            )
    de = kwargs.get("descriptor")
    if de is not None and de.path:  # a user's network: relative to the project, like annotations
        net = Path(de.path.replace("{data_root}", str(root))).expanduser()
        kwargs["descriptor"] = dataclasses.replace(
            de, path=str(net if net.is_absolute() else base / net)
        )
    cfg = Config(
        name=str(doc["name"]),
        data_root=root,
        annotations=ann,
        sessions=tuple(sessions),
        seed=seed,
        **kwargs,
    )
    if "localizers" in doc:
        cfg = dataclasses.replace(
            cfg, localizers=parse_localizers(doc["localizers"], cfg, base, root, where)
        )
    validate(cfg, where)
    for i, loc in enumerate(cfg.localizers):
        if loc.descriptor is not None:  # the [descriptor] checks, on the localizer's table
            try:
                validate(dataclasses.replace(cfg, descriptor=loc.descriptor, localizers=()), where)
            except ConfigError as err:
                raise ConfigError(
                    str(err).replace("[descriptor]", f"localizers[{i}] ({loc.name}) descriptor")
                ) from None
    return cfg


_LOCALIZER_KEYS = ("name", "proposals", "descriptor", "bovw", "import")


def parse_localizers(
    items: Any, cfg: Config, base: Path, root: Path, where: str
) -> tuple[LocalizerConfig, ...]:
    """The ``[[localizers]]`` array (SPEC section 11), each entry checked.

    Raises:
        ConfigError: naming the entry and what is wrong.
    """
    if not isinstance(items, list) or not items:
        raise ConfigError(f"{where}: 'localizers' must be a non-empty array of tables")
    out: list[LocalizerConfig] = []
    for i, item in enumerate(items):
        at = f"{where}: localizers[{i}]"
        if not isinstance(item, dict):
            raise ConfigError(f"{at}: expected a table, got {type(item).__name__}")
        unknown = sorted(set(item) - set(_LOCALIZER_KEYS))
        if unknown:
            raise ConfigError(f"{at}: unknown key(s) {unknown}; known: {list(_LOCALIZER_KEYS)}")
        name = item.get("name")
        if not isinstance(name, str) or not LOCALIZER_NAME.match(name):
            raise ConfigError(
                f"{at} name = {name!r}: expected a name of letters, digits, '.', '_', '-', '+' "
                "(it names the localizer in every table)"
            )
        ways = [k for k in ("descriptor", "bovw", "import") if k in item]
        if len(ways) != 1:
            raise ConfigError(
                f"{at} ({name}): give exactly one of descriptor, bovw or import; got "
                f"{ways or 'none'}"
            )
        props = _coerce(item.get("proposals", list(cfg.proposals.methods)), tuple[str, ...], at)
        bad = [m for m in props if m not in cfg.proposals.methods]
        if bad or not props:
            raise ConfigError(
                f"{at} ({name}) proposals = {list(props)}: each must be one of [proposals] "
                f"methods {list(cfg.proposals.methods)} (proposals are computed once, shared)"
            )
        kind = ways[0]
        de = bw = im = None
        if kind == "descriptor":
            de = _build(DescriptorConfig, item[kind], f"{at}.descriptor")
            if de.path:
                net = Path(de.path.replace("{data_root}", str(root))).expanduser()
                de = dataclasses.replace(de, path=str(net if net.is_absolute() else base / net))
        elif kind == "bovw":
            bw = _build(BovwConfig, item[kind], f"{at}.bovw")
            _check_bovw(bw, f"{at}.bovw")
        else:
            im = _build(LocalizerImportConfig, item[kind], f"{at}.import")
            f = Path(im.file.replace("{data_root}", str(root))).expanduser()
            im = dataclasses.replace(im, file=str(f if f.is_absolute() else base / f))
            _check(
                im.score_kind in ("distance", "similarity"),
                at,
                "import.score_kind",
                im.score_kind,
                "'distance' or 'similarity'",
            )
        out.append(LocalizerConfig(str(name), kind, tuple(props), de, bw, im))
    names = [x.name for x in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: [[localizers]] names must be unique, got {names}")
    if ALL_LOCALIZERS in names:
        raise ConfigError(f"{where}: {ALL_LOCALIZERS!r} names the fused block; choose another")
    return tuple(out)


#: A localizer's name: it heads tables and names files (never a path).
LOCALIZER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,63}$")
#: The name of the cross-localizer block (SPEC section 11).
ALL_LOCALIZERS = "all localizers"


def _check_bovw(bw: BovwConfig, where: str) -> None:
    """Ranges of a ``bovw`` table."""
    c = _check
    c(bw.features in ("sift", "rootsift", "orb"), where, "features", bw.features,
      "'sift', 'rootsift' or 'orb'")  # fmt: skip
    c(2 <= bw.k <= 1_000_000, where, "k", bw.k, "[2, 1e6]")
    c(bw.step >= 1, where, "step", bw.step, ">= 1")
    c(bw.patch >= 4, where, "patch", bw.patch, ">= 4")
    c(bw.input_size >= 16, where, "input_size", bw.input_size, ">= 16")
    c(bw.max_train_subimages >= 1, where, "max_train_subimages", bw.max_train_subimages, ">= 1")
    c(bw.max_train_features >= bw.k, where, "max_train_features", bw.max_train_features,
      f">= k ({bw.k})")  # fmt: skip
    c(bw.kmeans_iter >= 1, where, "kmeans_iter", bw.kmeans_iter, ">= 1")
    c(bw.seed >= 0, where, "seed", bw.seed, ">= 0")
    c(bw.shard_frames >= 1, where, "shard_frames", bw.shard_frames, ">= 1")


#: A session name is a directory name under ``--out``: letters, digits, ``.``, ``_``, ``-``, not
#: starting with a dot (so never ``..``, never a path).
SESSION_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def check_session_name(name: object, where: str) -> str:
    """A session (or camera) name that is safe as one directory or file name under ``--out``.

    Raises:
        ConfigError: The name is not a string, or holds a path separator, starts with a dot or
            another character outside letters, digits, ``.``, ``_`` and ``-``.
    """
    if not isinstance(name, str) or not SESSION_NAME.match(name):
        raise ConfigError(
            f"{where} = {name!r}: it names a directory or file the harness writes under --out, "
            "so it must be letters, digits, '.', '_' or '-', not start with '.' or '-', and "
            "hold no '/'"
        )
    return name


def _check(ok: bool, where: str, key: str, value: Any, allowed: str) -> None:
    if not ok:
        raise ConfigError(f"{where}: {key} = {value!r} is out of range; allowed: {allowed}")


def _range(
    where: str, key: str, pair: tuple[float, float], lo: float = 0.0, hi: float = 1.0
) -> None:
    _check(
        lo <= pair[0] <= pair[1] <= hi,
        where,
        key,
        list(pair),
        f"[low, high] with {lo} <= low <= high <= {hi}",
    )


def validate(cfg: Config, where: str) -> None:
    """Range checks that a dataclass cannot express, all at load time, before any work.

    Raises:
        ConfigError: naming the key, the value and the allowed range.
    """
    c = _check
    fu, pa, ig, de, re_, sp, rp, fx, pr = (
        cfg.fusion,
        cfg.pairs,
        cfg.ingest,
        cfg.descriptor,
        cfg.retrieval,
        cfg.splits,
        cfg.report,
        cfg.fixture,
        cfg.proposals,
    )
    fusion_methods = known_fusion_methods  # SPEC section 7's and registered ones

    c(
        cfg.import_.score_kind in ("distance", "similarity"),
        where,
        "[import] score_kind",
        cfg.import_.score_kind,
        "'distance' or 'similarity'",
    )
    bad = [m for m in fu.methods if m not in fusion_methods()]
    c(
        not bad and len(fu.methods) > 0,
        where,
        "[fusion] methods",
        list(fu.methods),
        f"a non-empty list of {list(fusion_methods())}",
    )
    c(
        len(set(fu.methods)) == len(fu.methods),
        where,
        "[fusion] methods",
        list(fu.methods),
        "each method once",
    )
    c(fu.max_fused_boxes >= 1, where, "[fusion] max_fused_boxes", fu.max_fused_boxes, ">= 1")
    c(
        0 < pa.max_yaw_diff_deg <= 180,
        where,
        "[pairs] max_yaw_diff_deg",
        pa.max_yaw_diff_deg,
        "(0, 180]",
    )
    c(
        pa.max_distance_m is None or pa.max_distance_m > 0,
        where,
        "[pairs] max_distance_m",
        pa.max_distance_m,
        "> 0 metres",
    )
    c(pa.stride_m >= 0, where, "[pairs] stride_m", pa.stride_m, ">= 0 metres")
    c(
        pa.queries in ("annotated", "all"),
        where,
        "[pairs] queries",
        pa.queries,
        "'annotated' or 'all'",
    )
    c(ig.max_pose_gap_s > 0, where, "[ingest] max_pose_gap_s", ig.max_pose_gap_s, "> 0 seconds")
    c(ig.max_image_pixels >= 1, where, "[ingest] max_image_pixels", ig.max_image_pixels, ">= 1")
    c(ig.max_tf_gap_s > 0, where, "[ingest] max_tf_gap_s", ig.max_tf_gap_s, "> 0 seconds")
    c(
        ig.time_source in ("header", "log"),
        where,
        "[ingest] time_source",
        ig.time_source,
        "'header' or 'log'",
    )
    c(
        ig.store_format in ("tiff", "png"),
        where,
        "[ingest] store_format",
        ig.store_format,
        "'tiff' or 'png'",
    )
    c(
        ig.nclt_rotation in ("cw", "ccw", "none"),
        where,
        "[ingest] nclt_rotation",
        ig.nclt_rotation,
        "cw, ccw or none",
    )
    c(
        re_.engine in ("exact", "faiss"),
        where,
        "[retrieval] engine",
        re_.engine,
        "'exact' or 'faiss'",
    )
    c(
        re_.db_stride_m >= 0,
        where,
        "[retrieval] db_stride_m",
        re_.db_stride_m,
        ">= 0 metres (0: every reference frame)",
    )
    c(
        re_.gt_radius_m >= 0,
        where,
        "[retrieval] gt_radius_m",
        re_.gt_radius_m,
        ">= 0 metres (0: the ground-truth frame alone)",
    )
    for key in ("chunk_rows", "query_batch", "faiss_nprobe", "query_frames_per_shard"):
        c(getattr(re_, key) >= 1, where, f"[retrieval] {key}", getattr(re_, key), ">= 1")
    c(re_.memory_mb > 0, where, "[retrieval] memory_mb", re_.memory_mb, "> 0 MiB")
    for key in ("faiss_nlist", "faiss_check"):
        c(getattr(re_, key) >= 0, where, f"[retrieval] {key}", getattr(re_, key), ">= 0")
    pj = cfg.projection
    c(pj.dim >= 0, where, "[projection] dim", pj.dim, ">= 0 (0: the full descriptor)")
    c(
        pj.fit_samples >= max(pj.dim, 1),
        where,
        "[projection] fit_samples",
        pj.fit_samples,
        f">= dim ({pj.dim}) and >= 1",
    )
    c(
        de.input_norm in ("none", "per_crop"),
        where,
        "[descriptor] input_norm",
        de.input_norm,
        "'none' or 'per_crop'",
    )
    c(
        de.dtype in ("float16", "float32"),
        where,
        "[descriptor] dtype",
        de.dtype,
        "float16 or float32",
    )
    c(
        de.device in ("auto", "cpu", "cuda") or de.device.startswith("cuda:"),
        where,
        "[descriptor] device",
        de.device,
        "auto, cpu, cuda or cuda:N",
    )
    c(
        de.train_samples >= 0,
        where,
        "[descriptor] train_samples",
        de.train_samples,
        ">= 0 (0: train for epochs)",
    )
    c(0 <= de.holdout < 1, where, "[descriptor] holdout", de.holdout, "[0, 1)")
    c(
        de.eval_every >= 1 and de.patience >= 1,
        where,
        "[descriptor] eval_every, patience",
        (de.eval_every, de.patience),
        ">= 1 each",
    )
    c(
        de.encode_batch >= 0,
        where,
        "[descriptor] encode_batch",
        de.encode_batch,
        ">= 0 (0: automatic)",
    )
    for key in ("epochs", "batch_size", "max_train_subimages", "shard_frames"):
        c(getattr(de, key) >= 1, where, f"[descriptor] {key}", getattr(de, key), ">= 1")
    c(de.num_workers >= 0, where, "[descriptor] num_workers", de.num_workers, ">= 0")
    c(
        de.input_size >= 8 and de.input_size % 8 == 0,
        where,
        "[descriptor] input_size",
        de.input_size,
        "a multiple of 8, >= 8 pixels",
    )
    c(de.lr > 0, where, "[descriptor] lr", de.lr, "> 0")
    c(
        de.pooling in ("avg", "max", "gem"),
        where,
        "[descriptor] pooling",
        de.pooling,
        "avg, max, gem",
    )
    c(de.gem_p > 0, where, "[descriptor] gem_p", de.gem_p, "> 0")
    c(all(v > 0 for v in de.std), where, "[descriptor] std", list(de.std), "three values > 0")
    if de.name in ("torchscript", "onnx"):
        c(bool(de.path), where, "[descriptor] path", de.path, f"the local {de.name} file")
        c(
            Path(de.path).is_file(),
            where,
            "[descriptor] path",
            de.path,
            "an existing file (nothing is downloaded at run time)",
        )
    c(
        all(ch >= 1 for ch in de.channels),
        where,
        "[descriptor] channels",
        list(de.channels),
        "three integers >= 1",
    )
    known_methods = known_proposal_methods  # the registry (built-ins and registered methods)

    badp = [m for m in pr.methods if m not in known_methods()]
    c(
        not badp and len(pr.methods) > 0,
        where,
        "[proposals] methods",
        list(pr.methods),
        f"a non-empty list of {list(known_methods())}",
    )
    c(
        "file" not in pr.methods or bool(pr.file),
        where,
        "[proposals] file",
        pr.file,
        "a path to a box table (the method 'file' is listed)",
    )
    c(
        "yolo" not in pr.methods or bool(pr.yolo.weights),
        where,
        "[proposals.yolo] weights",
        pr.yolo.weights,
        "a local weights path (the method 'yolo' is listed)",
    )
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
    _device(pr.yolo.device, where, "[proposals.yolo] device")
    c(
        all(d >= 1 and d % 2 == 1 for d in pr.edges.dilations) and len(pr.edges.dilations) > 0,
        where,
        "[proposals.edges] dilations",
        list(pr.edges.dilations),
        "a non-empty list of odd kernel sizes >= 1",
    )
    for sub_name in ("edges", "mser"):
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
        _range(
            where,
            f"[proposals.{sub_name}] min_area_frac..max_area_frac",
            (sub.min_area_frac, sub.max_area_frac),
        )
    c(
        len(sp.roc_max) > 0,
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "a non-empty list of values in [0, 1]",
    )
    c(
        all(0 <= r <= 1 for r in sp.roc_max),
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "values in [0, 1]",
    )
    c(
        len(set(sp.roc_max)) == len(sp.roc_max),
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "distinct values",
    )
    _range(where, "[splits] pos_roc", sp.pos_roc)
    _range(where, "[splits] pos_sob", sp.pos_sob)
    _range(where, "[splits] neg_sob", sp.neg_sob)
    c(
        0 <= sp.neg_roc_min <= min(sp.roc_max),
        where,
        "[splits] neg_roc_min",
        sp.neg_roc_min,
        f"[0, min(roc_max) = {min(sp.roc_max)}]",
    )
    st_ = sp.sob_strata
    c(
        len(st_) >= 2
        and all(a < b for a, b in itertools.pairwise(st_))
        and st_[0] >= 0
        and st_[-1] <= 1,
        where,
        "[splits] sob_strata",
        list(st_),
        "at least two increasing edges in [0, 1]",
    )
    c(
        rp.bootstrap >= 0,
        where,
        "[report] bootstrap",
        rp.bootstrap,
        ">= 0 resamples (0: no intervals)",
    )
    c(0 < rp.ci < 1, where, "[report] ci", rp.ci, "(0, 1), e.g. 0.95")
    c(rp.gallery >= 0, where, "[report] gallery", rp.gallery, ">= 0 thumbnails per method and kind")
    c(
        0 <= rp.headline_roc_max <= 1,
        where,
        "[report] headline_roc_max",
        rp.headline_roc_max,
        "[0, 1] (the page falls back to the largest RoC-max written)",
    )
    c(rp.locmap_examples >= 0, where, "[report] locmap_examples", rp.locmap_examples, ">= 0")
    c(fx.render_scale >= 1, where, "[fixture] render_scale", fx.render_scale, ">= 1")
    c(fx.frames >= 1, where, "[fixture] frames", fx.frames, ">= 1")
    c(
        fx.width >= 8 and fx.height >= 8,
        where,
        "[fixture] width x height",
        (fx.width, fx.height),
        ">= 8 pixels each",
    )
    c(fx.objects >= 0, where, "[fixture] objects", fx.objects, ">= 0")
    c(fx.loop_scale > 0, where, "[fixture] loop_scale", fx.loop_scale, "> 0")
    c(
        not fx.formats or len(fx.formats) in (1, len(cfg.sessions)),
        where,
        "[fixture] formats",
        list(fx.formats),
        f"one format, or one per session ({len(cfg.sessions)})",
    )
    c(
        all(f in FIXTURE_FORMATS for f in fx.formats),
        where,
        "[fixture] formats",
        list(fx.formats),
        f"names from {list(FIXTURE_FORMATS)}",
    )
    _device(de.device, where, "[descriptor] device")


#: The log formats the fixture generator writes (``harness.fixture.generate.FORMATS``).
FIXTURE_FORMATS = ("nclt", "ros1", "ros2", "mcap", "ros2mcap", "mcaptf")


def _device(device: str, where: str, key: str) -> None:
    """A CUDA device asked for by name must exist on this machine (``auto`` falls back)."""
    if not device.startswith("cuda"):
        return
    import torch

    if not torch.cuda.is_available():
        raise ConfigError(
            f"{where}: {key} = {device!r}, but torch sees no CUDA device on this machine; use "
            "'auto' (CUDA where there is one, else the CPU) or 'cpu'"
        )


def load_config(path: Path, data_root: str | None = None) -> Config:
    """Read and validate a TOML config file.

    Raises:
        ConfigError: The file is missing, is not TOML, or has unknown or invalid keys.
    """
    path = Path(path)
    text = read_text(
        path, "config file", ConfigError
    )  # missing, a directory, unreadable, not UTF-8
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML: {err}") from None
    return parse_config(doc, project_root(path.parent), str(path), data_root)

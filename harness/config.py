"""Configuration: one frozen dataclass per stage, loaded from TOML with unknown keys rejected.

A config file is a TOML document; ``load_config`` resolves relative paths against the file's
directory's project root (the directory holding ``pyproject.toml`` above it, else the file's
directory) and substitutes ``{data_root}`` in session sources.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from .errors import ConfigError

T = TypeVar("T")

FUSION_METHODS = (
    "rank_fusion",
    "rank_fusion_le2",
    "rank_fusion_le3",
    "rank_no_fusion",
    "score_max",
    "score_sum",
)


@dataclass(frozen=True)
class SessionConfig:
    """One season log. ``source`` is an NCLT root, a ``.bag``, a ROS2 bag directory or an ``.mcap``."""

    name: str
    source: str
    season: str = ""
    format: str = "auto"
    camera: str = "Cam5"
    image_topic: str | None = None
    pose_topic: str | None = None
    tf_child_frame: str | None = None


@dataclass(frozen=True)
class IngestConfig:
    max_pose_gap_s: float = 0.1
    time_source: str = "header"  # header stamp of the image message, or "log" (bag receive time)
    nclt_rotation: str = "cw"  # how NCLT's stored images are turned upright: cw, ccw, none
    salvage: bool = False  # keep the messages read before a truncated or corrupt part
    store_format: str = "tiff"  # lossless image store for raw images from logs: tiff (fast) or png (smaller)


@dataclass(frozen=True)
class PairsConfig:
    max_yaw_diff_deg: float = 45.0
    max_distance_m: float | None = 10.0
    stride_m: float = 0.0
    queries: str = "annotated"  # "annotated": only annotated query frames; "all": every frame


@dataclass(frozen=True)
class YoloConfig:
    weights: str | None = None
    conf: float = 0.05
    iou: float = 0.7
    imgsz: int = 640
    batch: int = 8
    device: str = "auto"
    max_det: int = 100


@dataclass(frozen=True)
class MserConfig:
    max_boxes: int = 12
    min_area_frac: float = 0.01
    max_area_frac: float = 0.4
    nms_iou: float = 0.5
    work_width: int = 320


@dataclass(frozen=True)
class EdgesConfig:
    max_boxes: int = 12
    min_area_frac: float = 0.005
    max_area_frac: float = 0.4
    nms_iou: float = 0.5
    work_width: int = 480
    dilations: tuple[int, ...] = (3, 5, 9)


@dataclass(frozen=True)
class ProposalsConfig:
    methods: tuple[str, ...] = ("grid5", "edges")
    edges: EdgesConfig = field(default_factory=EdgesConfig)
    yolo: YoloConfig = field(default_factory=YoloConfig)
    mser: MserConfig = field(default_factory=MserConfig)
    file: str | None = None


@dataclass(frozen=True)
class DescriptorConfig:
    name: str = "autoencoder"
    input_size: int = 256
    channels: tuple[int, int, int] = (32, 32, 16)
    input_norm: str = "none"  # "none" (the paper) or "per_crop": standardise each crop's channels
    epochs: int = 4
    batch_size: int = 32  # training batch
    encode_batch: int = 0  # subimages per encoder call; 0: 2 on CPU (keeps activations in cache), batch_size on GPU
    lr: float = 1e-3
    max_train_subimages: int = 4000
    dtype: str = "float16"
    device: str = "auto"
    seed: int = 0
    num_workers: int = 0
    shard_frames: int = 256  # frames per cached descriptor shard (the unit an interrupted run resumes at)


@dataclass(frozen=True)
class RetrievalConfig:
    engine: str = "exact"  # exact or faiss
    chunk_rows: int = 8192
    query_batch: int = 1024
    faiss_nlist: int = 0  # 0: flat index; >0: IVF with that many lists
    faiss_nprobe: int = 8
    query_frames_per_shard: int = 512  # pairs per ranking unit (the unit mapped over executors)
    faiss_check: int = 256  # queries per engine also ranked exactly, to report faiss's recall


@dataclass(frozen=True)
class FusionConfig:
    methods: tuple[str, ...] = FUSION_METHODS
    seed: int = 0
    max_fused_boxes: int = 4096


@dataclass(frozen=True)
class SplitsConfig:
    roc_max: tuple[float, ...] = (0.01, 0.02, 0.03, 0.04, 0.05)
    pos_roc: tuple[float, float] = (0.9, 1.0)
    pos_sob: tuple[float, float] = (0.0, 0.4)
    neg_roc_min: float = 0.0
    neg_sob: tuple[float, float] = (0.4, 1.0)


@dataclass(frozen=True)
class ReportConfig:
    bootstrap: int = 1000
    ci: float = 0.95
    locmap_examples: int = 4
    plots: bool = True


@dataclass(frozen=True)
class FixtureConfig:
    """Generate the fixture into ``data_root`` when it is absent."""

    generate: bool = False
    seed: int = 0
    frames: int = 64
    width: int = 120
    height: int = 160
    objects: int = 3
    loop_scale: float = 1.5
    render_scale: int = 1  # ray-cast at 1/scale resolution and upsample (NCLT-sized frames cheaply)
    formats: tuple[str, ...] = ()  # log format per session; empty: nclt, ros1, ros2, mcap


@dataclass(frozen=True)
class Config:
    name: str
    data_root: Path
    annotations: Path
    sessions: tuple[SessionConfig, ...]
    seed: int = 0
    ingest: IngestConfig = field(default_factory=IngestConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    proposals: ProposalsConfig = field(default_factory=ProposalsConfig)
    descriptor: DescriptorConfig = field(default_factory=DescriptorConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    splits: SplitsConfig = field(default_factory=SplitsConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    fixture: FixtureConfig = field(default_factory=FixtureConfig)

    def seasons(self) -> dict[str, str]:
        from .records import season_of

        return {s.name: s.season or season_of(s.name) for s in self.sessions}


def _build(cls: type[T], data: Any, where: str) -> T:
    """Build dataclass ``cls`` from a dict, rejecting unknown keys and coercing lists to tuples."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(fields)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        ftype = fields[name].type
        sub = _NESTED.get((cls.__name__, name))
        if sub is not None:
            kwargs[name] = _build(sub, value, f"{where}.{name}")
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
        del ftype
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
    "fusion": FusionConfig,
    "splits": SplitsConfig,
    "report": ReportConfig,
    "fixture": FixtureConfig,
}


def project_root(start: Path) -> Path:
    """The nearest directory at or above ``start`` holding ``pyproject.toml`` (else ``start``)."""
    start = start.resolve()
    for d in (start, *start.parents):
        if (d / "pyproject.toml").exists():
            return d
    return start


def parse_config(doc: dict[str, Any], base: Path, where: str, data_root: str | None = None) -> Config:
    """Build a :class:`Config` from a parsed TOML document; relative paths resolve against ``base``."""
    top_keys = {"name", "data_root", "annotations", "sessions", "seed", *_SECTIONS}
    unknown = sorted(set(doc) - top_keys)
    if unknown:
        raise ConfigError(f"{where}: unknown top-level key(s) {unknown}; known: {sorted(top_keys)}")
    for required in ("name", "sessions", "annotations"):
        if required not in doc:
            raise ConfigError(f"{where}: missing required key {required!r}")
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
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: session names must be unique, got {names}")
    ann = Path(str(doc["annotations"]).replace("{data_root}", str(root))).expanduser()
    ann = ann if ann.is_absolute() else base / ann
    kwargs: dict[str, Any] = {}
    for section, cls in _SECTIONS.items():
        if section in doc:
            kwargs[section] = _build(cls, doc[section], f"{where}: [{section}]")
    cfg = Config(
        name=str(doc["name"]),
        data_root=root,
        annotations=ann,
        sessions=tuple(sessions),
        seed=int(doc.get("seed", 0)),
        **kwargs,
    )
    validate(cfg, where)
    return cfg


def validate(cfg: Config, where: str) -> None:
    """Range checks that a dataclass cannot express."""
    bad = [m for m in cfg.fusion.methods if m not in FUSION_METHODS]
    if bad:
        raise ConfigError(f"{where}: [fusion] unknown method(s) {bad}; known: {list(FUSION_METHODS)}")
    if not 0 < cfg.pairs.max_yaw_diff_deg <= 180:
        raise ConfigError(f"{where}: [pairs] max_yaw_diff_deg must be in (0, 180]")
    if cfg.pairs.queries not in ("annotated", "all"):
        raise ConfigError(f"{where}: [pairs] queries must be 'annotated' or 'all'")
    if cfg.ingest.time_source not in ("header", "log"):
        raise ConfigError(f"{where}: [ingest] time_source must be 'header' or 'log'")
    if cfg.ingest.store_format not in ("tiff", "png"):
        raise ConfigError(f"{where}: [ingest] store_format must be 'tiff' or 'png'")
    if cfg.ingest.nclt_rotation not in ("cw", "ccw", "none"):
        raise ConfigError(f"{where}: [ingest] nclt_rotation must be cw, ccw or none")
    if cfg.retrieval.engine not in ("exact", "faiss"):
        raise ConfigError(f"{where}: [retrieval] engine must be 'exact' or 'faiss'")
    if cfg.descriptor.input_norm not in ("none", "per_crop"):
        raise ConfigError(f"{where}: [descriptor] input_norm must be 'none' or 'per_crop'")
    if cfg.fixture.render_scale < 1:
        raise ConfigError(f"{where}: [fixture] render_scale must be >= 1")
    if cfg.fixture.formats and len(cfg.fixture.formats) not in (1, len(cfg.sessions)):
        raise ConfigError(f"{where}: [fixture] formats must name one format, or one per session ({len(cfg.sessions)})")
    if cfg.descriptor.encode_batch < 0:
        raise ConfigError(f"{where}: [descriptor] encode_batch must be >= 0 (0: automatic)")
    if cfg.descriptor.dtype not in ("float16", "float32"):
        raise ConfigError(f"{where}: [descriptor] dtype must be float16 or float32")
    if not cfg.proposals.methods:
        raise ConfigError(f"{where}: [proposals] methods must not be empty")
    if any(not 0 <= r <= 1 for r in cfg.splits.roc_max):
        raise ConfigError(f"{where}: [splits] roc_max values must lie in [0, 1]")


def load_config(path: Path, data_root: str | None = None) -> Config:
    """Read and validate a TOML config file.

    Raises:
        ConfigError: The file is missing, is not TOML, or has unknown or invalid keys.
    """
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"config file {path} does not exist")
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML: {err}") from None
    return parse_config(doc, project_root(path.parent), str(path), data_root)

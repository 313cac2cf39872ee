"""Configuration: one frozen dataclass per stage, loaded from TOML with unknown keys rejected.

A config file is a TOML document; ``read_config`` resolves relative paths against the file's
directory's project root (the directory holding ``pyproject.toml`` above it, else the file's
directory) and substitutes ``{data_root}`` in session sources.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from harness.config.plugins import load_plugins
from harness.config.schema import Config
from harness.descriptors.config import DescriptorConfig, ProjectionConfig
from harness.detect.config import DetectConfig
from harness.errors import ConfigError
from harness.evaluate.config import ReportConfig, SplitsConfig
from harness.fixture.config import FixtureConfig
from harness.fusion.config import FusionConfig
from harness.ingest.config import IngestConfig, MasksConfig, SessionConfig, check_session_name
from harness.inputs import read_text, resolve_config_path
from harness.localizers.config import ALL_LOCALIZERS, LocalConfig, LocalizerConfig
from harness.localizers.kinds import LOCALIZER_KINDS
from harness.methods import FUSION_OPTIONS, LOCALIZER_NAME_RULE, PROPOSER_OPTIONS, is_localizer_name
from harness.pairs.config import PairsConfig
from harness.proposals.config import (
    EdgesConfig,
    MserConfig,
    ProposalsConfig,
    SegmentsConfig,
    YoloConfig,
)
from harness.retrieval.config import ImportConfig, RetrievalConfig

__all__ = ["parse_config", "parse_localizers", "project_root", "read_config"]

T = TypeVar("T")


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
    extra: dict[str, Any] = {}
    if cls in _OPTION_TABLES:  # a registered method's own table, [proposals.<name>]
        data, extra = _method_options(data, _OPTION_TABLES[cls], where)
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(fields)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        sub = NESTED_TABLES.get((cls.__name__, name))
        hint = hints.get(name)
        if sub is None and isinstance(hint, type) and dataclasses.is_dataclass(hint):
            sub = hint  # a nested table typed by its dataclass ([detect.keypoints], [detect.null])
        if sub is not None:
            kwargs[name] = _build(sub, value, f"{where}.{name}")
        else:
            kwargs[name] = _coerce(value, hints[name], f"{where} {name}")
    if extra:
        kwargs["options"] = extra
    try:
        return cls(**kwargs)
    except TypeError as err:
        raise ConfigError(f"{where}: {err}") from None


def _method_options(
    data: dict[str, Any], registry: dict[str, type], where: str
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A section without the tables of registered methods, and those tables built.

    ``[proposals.<method>]`` and ``[fusion.<rule>]``: each registered method's options
    dataclass (``registry``) built from its table.
    """
    if "options" in data:
        raise ConfigError(f"{where}: unknown key(s) ['options']; a method's table is its name")
    mine = {k: v for k, v in data.items() if k in registry}
    rest = {k: v for k, v in data.items() if k not in registry}
    return rest, {k: _build(registry[k], v, f"{where}.{k}") for k, v in mine.items()}


#: Sections whose registered methods bring a table of their own.
_OPTION_TABLES: dict[type, dict[str, type]] = {
    ProposalsConfig: PROPOSER_OPTIONS,
    FusionConfig: FUSION_OPTIONS,
}


NESTED_TABLES: dict[tuple[str, str], type] = {
    ("ProposalsConfig", "yolo"): YoloConfig,
    ("ProposalsConfig", "mser"): MserConfig,
    ("ProposalsConfig", "edges"): EdgesConfig,
    ("ProposalsConfig", "segments"): SegmentsConfig,
    ("DetectConfig", "local"): LocalConfig,
}

SECTIONS: dict[str, type] = {
    "ingest": IngestConfig,
    "pairs": PairsConfig,
    "proposals": ProposalsConfig,
    "descriptor": DescriptorConfig,
    "retrieval": RetrievalConfig,
    "projection": ProjectionConfig,
    "fusion": FusionConfig,
    "splits": SplitsConfig,
    "report": ReportConfig,
    "detect": DetectConfig,
    "fixture": FixtureConfig,
    "import": ImportConfig,
    "masks": MasksConfig,
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


def _resolve_paths(kwargs: dict[str, Any], base: Path, root: Path) -> None:
    """A user's network and mask folder: relative to the project, like the annotations."""
    de = kwargs.get("descriptor")
    if de is not None and de.path:
        net = resolve_config_path(de.path, base, root)
        kwargs["descriptor"] = de = dataclasses.replace(de, path=str(net))
    if de is not None and de.trained_models:
        kept = resolve_config_path(de.trained_models, base, root)
        kwargs["descriptor"] = dataclasses.replace(de, trained_models=str(kept))
    mk = kwargs.get("masks")
    if mk is not None and mk.folder:
        kwargs["masks"] = dataclasses.replace(
            mk, folder=str(resolve_config_path(mk.folder, base, root))
        )


def parse_config(
    doc: dict[str, Any],
    base: Path,
    where: str,
    data_root: str | None = None,
    settings_only: bool = False,
) -> Config:
    """Build a :class:`Config` from a parsed TOML document.

    Relative paths resolve against ``base``. ``settings_only``: the document gives settings for
    sessions named elsewhere (two image folders): ``name`` and ``sessions`` may be left out.
    """
    if settings_only:  # sessions named elsewhere: a name and a session stand in for them
        doc = {"name": "settings", "sessions": [{"name": "folder", "source": "."}], **doc}
    top_keys = {"name", "data_root", "annotations", "sessions", "seed", "localizers", "plugins"}
    top_keys |= set(SECTIONS)
    unknown = sorted(set(doc) - top_keys)
    if unknown:
        raise ConfigError(f"{where}: unknown top-level key(s) {unknown}; known: {sorted(top_keys)}")
    plugins = doc.get("plugins", [])
    if not isinstance(plugins, list) or not all(isinstance(p, str) for p in plugins):
        raise ConfigError(f"{where}: plugins = {plugins!r}: expected a list of .py file paths")
    load_plugins([base / Path(p).expanduser() for p in plugins], f"{where}: plugins")
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
        src = resolve_config_path(sc.source, base, root)
        sessions.append(dataclasses.replace(sc, source=str(src)))
    for i, sc in enumerate(sessions):
        check_session_name(sc.name, f"{where}: sessions[{i}] name")
        check_session_name(sc.camera, f"{where}: sessions[{i}] camera")
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: session names must be unique, got {names}")
    ann: Path | None = None
    if "annotations" in doc:
        ann = resolve_config_path(str(doc["annotations"]), base, root)
    kwargs: dict[str, Any] = {}
    for section, cls in SECTIONS.items():
        if section in doc:
            kwargs[_FIELD.get(section, section)] = _build(
                cls, doc[section], f"{where}: [{section}]"
            )
    _resolve_paths(kwargs, base, root)
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
    return cfg


def _kind_names() -> str:
    """``descriptor, bovw or import`` (and any registered kind)."""
    names = list(LOCALIZER_KINDS)
    return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else names[0]


def parse_localizers(
    items: Any, cfg: Config, base: Path, root: Path, where: str
) -> tuple[LocalizerConfig, ...]:
    """The ``[[localizers]]`` array (method §11), each entry checked.

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
        known = ["name", "proposals", *LOCALIZER_KINDS]
        unknown = sorted(set(item) - set(known))
        if unknown:
            raise ConfigError(f"{at}: unknown key(s) {unknown}; known: {known}")
        name = item.get("name")
        if not is_localizer_name(name):
            raise ConfigError(
                f"{at} name = {name!r}: expected {LOCALIZER_NAME_RULE} (it names the localizer "
                "in every table)"
            )
        ways = [k for k in LOCALIZER_KINDS if k in item]
        if len(ways) != 1:
            raise ConfigError(
                f"{at} ({name}): give exactly one of {_kind_names()}; got {ways or 'none'}"
            )
        props = _coerce(item.get("proposals", list(cfg.proposals.methods)), tuple[str, ...], at)
        bad = [m for m in props if m not in cfg.proposals.methods]
        if bad or not props:
            raise ConfigError(
                f"{at} ({name}) proposals = {list(props)}: each must be one of [proposals] "
                f"methods {list(cfg.proposals.methods)} (proposals are computed once, shared)"
            )
        kind = LOCALIZER_KINDS[ways[0]]
        options: Any = _build(kind.options, item[kind.name], f"{at}.{kind.name}")
        if kind.prepare is not None:
            options = kind.prepare(options, at, base, root)
        out.append(LocalizerConfig(str(name), kind.name, tuple(props), options))
    names = [x.name for x in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: [[localizers]] names must be unique, got {names}")
    if ALL_LOCALIZERS in names:
        raise ConfigError(f"{where}: {ALL_LOCALIZERS!r} names the fused block; choose another")
    return tuple(out)


def read_config(path: Path, data_root: str | None = None, settings_only: bool = False) -> Config:
    """Read a TOML config file into a :class:`Config` (``settings_only``: see :func:`parse_config`).

    Its types and keys are checked here; its ranges where the run's config is assembled, once
    (:func:`harness.config.assemble.load_config`).

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
    return parse_config(doc, project_root(path.parent), str(path), data_root, settings_only)

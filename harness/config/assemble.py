"""A run's config, assembled in one place.

The file (or the image folders), then what the command line sets over it, then validation.
Nothing downstream edits what these functions return; a ``harness detect`` run derives the config
its pipeline runs from it in one named step (:func:`detect_run_config`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from harness.config.check import validate
from harness.config.folders import image_folders_config
from harness.config.load import read_config
from harness.config.schema import Config
from harness.detect.config import CONFIG_LOCALIZERS, DetectConfig
from harness.detect.presets import PRESETS
from harness.errors import AnnotationError, ConfigError
from harness.inputs import check_input


@dataclass(frozen=True)
class Overrides:
    """What a command line sets over its config; None (or empty) where nothing was typed.

    ``detect``: ``[detect]`` values as typed, by field name, each winning over ``preset``'s
    (``harness detect --preset``, docs/detect.md), which wins over the config's.
    """

    data_root: str | None = None
    seed: int | None = None
    annotations: Path | None = None
    masks: Path | None = None
    preset: str | None = None
    detect: Mapping[str, Any] = field(default_factory=dict)


def flag_of(name: str) -> str:
    """The command-line flag of ``[detect]`` field ``name``."""
    return "--" + name.replace("_", "-")


def with_overrides(cfg: Config, ov: Overrides, where: str, command: str = "") -> Config:
    """``cfg`` with ``ov`` in place of its own values, validated: the one place a config is.

    ``where``: the file (or folders) ``cfg`` came from, named in an error about its values;
    ``command``: the command whose typed flags ``ov`` holds, named in an error about one of them.

    Raises:
        ConfigError: a value out of range (naming its key and ``where``, or its flag and
            ``command``), or an unknown preset.
        AnnotationError: ``--annotations`` or ``--masks`` is not there.
    """
    out = cfg if ov.seed is None else dataclasses.replace(cfg, seed=ov.seed)
    if ov.annotations is not None:
        path = check_input(Path(ov.annotations), "annotation file", AnnotationError)
        out = dataclasses.replace(out, annotations=Path(path).resolve())
    if ov.masks is not None:
        d = check_input(Path(ov.masks), "mask folder", AnnotationError, directory=True)
        masks = dataclasses.replace(out.masks, folder=str(Path(d).resolve()))
        out = dataclasses.replace(out, masks=masks)
    if ov.preset is not None or ov.detect:
        if ov.preset is not None and ov.preset not in PRESETS:
            raise ConfigError(f"--preset {ov.preset!r}: one of {', '.join(PRESETS)}")
        values = {**(PRESETS[ov.preset][1] if ov.preset else {}), **ov.detect}
        out = dataclasses.replace(out, detect=dataclasses.replace(out.detect, **values))
    typed = {k: flag_of(k) for k in ov.detect}
    if ov.seed is not None:
        typed["seed"] = "--seed"
    validate(out, where, typed, command or "the command line")  # checked once, then frozen
    return out


def load_config(path: Path, data_root: str | None = None, settings_only: bool = False) -> Config:
    """Read and validate a TOML config file, nothing set over it.

    ``data_root``: in place of the file's; ``settings_only``: the sessions come from elsewhere,
    so the file may name none (:func:`harness.config.load.parse_config`).

    Raises:
        ConfigError: The file is missing, is not TOML, or has unknown or invalid keys.
    """
    return with_overrides(read_config(Path(path), data_root, settings_only), Overrides(), str(path))


def run_config(path: Path, ov: Overrides, settings_only: bool = False, command: str = "") -> Config:
    """The config of ``--config PATH`` with ``ov`` applied.

    ``settings_only``: the sessions come from elsewhere, so the file may name none.
    """
    cfg = read_config(Path(path), ov.data_root, settings_only)
    return with_overrides(cfg, ov, str(path), command)


def folders_config(
    map_dir: Path, query_dirs: list[Path], settings: Path | None, ov: Overrides, command: str = ""
) -> tuple[Config, str, list[str]]:
    """The config of two (or more) folders of images, and the map and query sessions' names.

    The settings are those of ``settings`` (a ``--config``) where given; ``ov`` applied.
    """
    base = read_config(Path(settings), ov.data_root, True) if settings is not None else None
    cfg, m, q = image_folders_config(Path(map_dir), list(query_dirs), base)
    where = str(settings) if settings is not None else "--map-images/--query-images"
    return with_overrides(cfg, ov, where, command), m, q


def detect_run_config(
    cfg: Config, map_session: str, query_sessions: list[str], opt: DetectConfig
) -> Config:
    """The config a ``harness detect`` run's pipeline runs (method §13).

    Derived from the assembled ``cfg`` and its detector ``opt`` (``cfg.detect`` from the command
    line): the map and query sessions alone, every query frame, and the paired localizer's
    proposals beside the config's.
    """
    keep = [s for s in cfg.sessions if s.name in (map_session, *query_sessions)]
    out = dataclasses.replace(
        cfg, sessions=tuple(keep), pairs=dataclasses.replace(cfg.pairs, queries="all")
    )
    if opt.localizer != CONFIG_LOCALIZERS and opt.proposals not in cfg.proposals.methods:
        out = dataclasses.replace(
            out,
            proposals=dataclasses.replace(
                cfg.proposals, methods=(*cfg.proposals.methods, opt.proposals)
            ),
            # the config's localizers (pairs by retrieval or sequence) keep their own proposals
            localizers=cfg.localizer_set(),
        )
    return out

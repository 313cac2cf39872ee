"""Localizer kinds (SPEC section 11): one ``[[localizers]]`` sub-table each, registered alike.

A kind is its options' dataclass (the sub-table, read by the same typed loader as every table),
an optional ``prepare`` that checks them and resolves their paths at load time, what ``run.json``
says of them, and its ranks function, attached by :mod:`harness.pipeline.localizer_stages`
(``@kind_ranks(name)``) or given at registration. A fourth built-in kind is its record here and
its ranks there; a user's kind is one :func:`register_localizer_kind` call.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.checks import check_value
from harness.descriptors.config import DescriptorConfig
from harness.errors import ConfigError
from harness.inputs import resolve_config_path
from harness.localizers.config import LocalConfig, LocalizerImportConfig, check_local
from harness.methods import Registry
from harness.retrieval.config import BovwConfig, check_bovw

__all__ = ["LOCALIZER_KINDS", "LocalizerKind", "register_localizer_kind"]

#: (options, the entry's place in the config, the config file's folder, data_root) -> the options,
#: checked and resolved.
Prepare = Callable[[Any, str, Path, Path], Any]


@dataclass(frozen=True)
class LocalizerKind:
    """One localizer kind: its ``[[localizers]]`` sub-table and how it ranks."""

    #: The sub-table's key in a ``[[localizers]]`` entry (``descriptor = {...}``).
    name: str
    #: The options' dataclass: the sub-table's keys are its fields.
    options: type
    #: Checks the options and resolves their paths at load time; None: as loaded.
    prepare: Prepare | None = None
    #: What ``run.json`` and the page say of the options; None: ``{name: asdict(options)}``.
    record: Callable[[Any], dict[str, Any]] | None = None
    #: (context, localizer, frames, pairs, its proposals) -> its rank rows; None until attached.
    ranks: Callable[..., Any] | None = None

    def describe(self, options: Any) -> dict[str, Any]:
        """``run.json``'s fields for ``options`` of this kind."""
        if self.record is not None:
            return self.record(options)
        return {self.name: dataclasses.asdict(options)}


def _descriptor(de: DescriptorConfig, where: str, base: Path, root: Path) -> DescriptorConfig:
    return (
        dataclasses.replace(de, path=str(resolve_config_path(de.path, base, root)))
        if de.path
        else de
    )


def _bovw(bw: BovwConfig, where: str, base: Path, root: Path) -> BovwConfig:
    check_bovw(bw, f"{where}.bovw")
    return bw


def _import(im: LocalizerImportConfig, where: str, base: Path, root: Path) -> LocalizerImportConfig:
    check_value(
        im.score_kind in ("distance", "similarity"),
        where,
        "import.score_kind",
        im.score_kind,
        "'distance' or 'similarity'",
    )
    return dataclasses.replace(im, file=str(resolve_config_path(im.file, base, root)))


def _local(lc: LocalConfig, where: str, base: Path, root: Path) -> LocalConfig:
    return check_local(lc, f"{where}.local")


def _name_only(de: DescriptorConfig) -> dict[str, Any]:
    return {"descriptor": de.name}


#: Kind name -> its record, in the order the config's error messages list them.
LOCALIZER_KINDS: Registry[LocalizerKind] = Registry("localizer kind", ("name", "proposals"))
for _kind in (
    LocalizerKind("descriptor", DescriptorConfig, _descriptor, _name_only),
    LocalizerKind("bovw", BovwConfig, _bovw),
    LocalizerKind("import", LocalizerImportConfig, _import),
    LocalizerKind("local", LocalConfig, _local),
):
    LOCALIZER_KINDS.add(_kind.name, _kind)


def register_localizer_kind(kind: LocalizerKind) -> None:
    """Add ``kind`` (a ``[[localizers]]`` sub-table ``kind.name = {...}``) before the config loads.

    Raises:
        ConfigError: a name already taken, or no ranks function.
    """
    if kind.ranks is None:
        raise ConfigError(f"localizer kind {kind.name!r}: give its ranks function")
    LOCALIZER_KINDS.add(kind.name, kind, ConfigError)

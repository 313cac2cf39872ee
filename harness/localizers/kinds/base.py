"""A localizer kind's record, the registry of them, and the run its ranks function is given.

A kind is its options' dataclass (the sub-table, read by the same typed loader as every table),
an optional ``prepare`` that checks them and resolves their paths at load time, what ``run.json``
says of them, and its ranks function. The built-in kinds are one module each beside this one; a
user's kind is one :func:`register_localizer_kind` call.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from harness.descriptors.config import DescriptorConfig
from harness.errors import ConfigError
from harness.localizers.config import (
    LocalizerConfig,
)
from harness.methods import Registry
from harness.retrieval.config import RetrievalConfig
from harness.retrieval.import_file import ImportSpec
from harness.runtime.stage import Entry, RankTable, Table, Units

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
    #: (the run, localizer, frames, pairs, its proposals, ``[retrieval]``) -> its rank rows
    #: (:data:`KindRanks`).
    ranks: Callable[..., Any] | None = None
    #: Adjusts Table L's cost cells of a localizer of this kind in place, given the frame table
    #: and the pairs (what its map holds, what it encodes); None: as measured.
    costs: Callable[[dict[str, float], Any, Any], None] | None = None
    #: What the report page says of a localizer of this kind, from its ``run.json`` record and the
    #: run's config (as a dict); None: its kind's name.
    summary: Callable[[dict[str, Any], dict[str, Any]], str] | None = None
    #: Whether it ranks each query box inside its paired map frame alone (needing no map beyond
    #: that frame): ``harness detect`` can then rank with it, and its no-change null score pairs.
    paired_frame: bool = False

    def describe(self, options: Any) -> dict[str, Any]:
        """``run.json``'s fields for ``options`` of this kind."""
        if self.record is not None:
            return self.record(options)
        return {self.name: dataclasses.asdict(options)}


#: Kind name -> its record, in the order the config's error messages list them.
LOCALIZER_KINDS: Registry[LocalizerKind] = Registry("localizer kind", ("name", "proposals"))


def paired_kinds() -> tuple[str, ...]:
    """The kinds that rank a box inside its paired map frame, in registration order."""
    return tuple(k for k, v in LOCALIZER_KINDS.items() if v.paired_frame)


class LocalizerRun(Units, Protocol):
    """The run a kind's ranks function is given (:class:`harness.pipeline.context.Context`).

    The stages it builds its entries with (:class:`harness.runtime.stage.Units`), and the stages
    of the harness a kind may reuse, with the run's config sections: the descriptor's model and
    projection, the ranking engine, an import's checks.
    """

    @property
    def descriptor_device(self) -> str:
        """The run's ``[descriptor] device``."""
        ...

    def descriptor_model(
        self, dc: DescriptorConfig, frames: Table, props: dict[str, Table]
    ) -> Entry:
        """The trained model of ``dc`` on the run's training sessions' proposals."""
        ...

    def descriptor_projection(
        self,
        dc: DescriptorConfig,
        frames: Table,
        pairs: Table,
        props: dict[str, Table],
        model: Entry,
    ) -> Entry | None:
        """The compact-descriptor projection under the run's ``[projection]``."""
        ...

    def query_ranks(
        self,
        frames: Table,
        pairs: Table,
        described: dict[str, Entry],
        rc: RetrievalConfig,
        device: str = "auto",
        precision: str = "fp32",
    ) -> RankTable:
        """The rank of each query subimage's true place, by the harness's ranking engine."""
        ...

    def imported_ranks(
        self,
        frames: Table,
        pairs: Table,
        props: dict[str, Table],
        spec: ImportSpec,
        score_kind: str,
        rc: RetrievalConfig,
    ) -> RankTable:
        """Ranks from a user's file, checked against the run."""
        ...


#: A kind's rank rows: (the run, localizer, frames, pairs, its proposals, the ``[retrieval]``
#: whose ground-truth place it ranks against) -> ranks.
KindRanks = Callable[
    [LocalizerRun, LocalizerConfig, Table, Table, dict[str, Table], RetrievalConfig], RankTable
]


def kind_summary(record: dict[str, Any], cfg: dict[str, Any]) -> str:
    """What the report page says of a localizer (its ``run.json`` record): its kind's words.

    A kind this interpreter does not know (a plugin's, read back without it) is named.
    """
    kind = LOCALIZER_KINDS.get(str(record.get("kind")))
    if kind is None or kind.summary is None:
        return f"localizer kind {record.get('kind')}"
    return kind.summary(record, cfg)


T = TypeVar("T")


def options_of(loc: LocalizerConfig, value: T | None) -> T:
    """A localizer's options of its kind (the config loader sets them for that kind).

    Raises:
        ConfigError: they are missing (a config built by hand without them).
    """
    if value is None:
        raise ConfigError(f"localizer {loc.name!r} of kind {loc.kind!r}: its options are missing")
    return value


def register_localizer_kind(kind: LocalizerKind) -> None:
    """Add ``kind`` (a ``[[localizers]]`` sub-table ``kind.name = {...}``) before the config loads.

    Raises:
        ConfigError: a name already taken, or no ranks function.
    """
    if kind.ranks is None:
        raise ConfigError(f"localizer kind {kind.name!r}: give its ranks function")
    LOCALIZER_KINDS.add(kind.name, kind, ConfigError)

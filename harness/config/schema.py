"""The run's root configuration: one section per stage, each defined and checked beside its stage.

Loaded and checked by :mod:`harness.config.load` (TOML, unknown keys rejected) and
:mod:`harness.config.check` (ranges, at load time). A section's dataclass lives in its stage's
package (``harness/<stage>/config.py``); this module only assembles them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from harness.descriptors.config import DescriptorConfig, ProjectionConfig
from harness.detect.config import DetectConfig
from harness.evaluate.config import ReportConfig, SplitsConfig
from harness.fixture.config import FixtureConfig
from harness.fusion.config import FusionConfig
from harness.ingest.config import IngestConfig, MasksConfig, SessionConfig
from harness.localizers.config import LocalizerConfig
from harness.pairs.config import PairsConfig
from harness.proposals.config import ProposalsConfig
from harness.records import season_of
from harness.retrieval.config import ImportConfig, RetrievalConfig


@dataclass(frozen=True)
class Config:
    """A whole run's configuration, as loaded from TOML and checked (:func:`load_config`)."""

    # the run's name: its tables' and page's title
    name: str
    # where the sessions' sources are; {data_root} in a source is this (harness reproduce --data-
    # root overrides it)
    data_root: Path
    annotations: Path | None  # None: no annotation file (harness detect only)
    # [[sessions]]: the season logs, one table each (the first is the map where a command names
    # none)
    sessions: tuple[SessionConfig, ...]
    # the run's seed: the fixture, the training, the floors' random orders
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

"""What a ``harness detect`` run starts before its modules load: Selective Search's workers.

Kept apart from :mod:`harness.apps.detect`, which imports every stage: the command line calls this
first, so the worker processes load their modules while the run's own load (a second or so).
"""

from __future__ import annotations

from harness.config.schema import Config
from harness.detect.config import CONFIG_LOCALIZERS
from harness.proposals.proposers import start_workers


def start_detect_workers(cfg: Config) -> None:
    """Start the proposal workers the run's methods and its paired localizer's proposals use."""
    paired = () if cfg.detect.localizer == CONFIG_LOCALIZERS else (cfg.detect.proposals,)
    start_workers(cfg.proposals, (*cfg.proposals.methods, *paired))

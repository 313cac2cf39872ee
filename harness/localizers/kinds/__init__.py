"""Localizer kinds (method §11): one ``[[localizers]]`` sub-table each, registered alike.

:mod:`.base` holds the record (:class:`LocalizerKind`), the registry and the run a kind's ranks
function is given; the built-in kinds are one module each, its record (``KIND``) and its ranks
together, added here in the order the config's error messages list them. A user's kind is one
:func:`register_localizer_kind` call.
"""

from __future__ import annotations

from harness.localizers.kinds import bovw, descriptor, imported, keypoints, local
from harness.localizers.kinds.base import (
    LOCALIZER_KINDS,
    KindRanks,
    LocalizerKind,
    LocalizerRun,
    kind_summary,
    options_of,
    paired_kinds,
    register_localizer_kind,
)
from harness.localizers.kinds.paired import paired_frame_kind

for _module in (descriptor, bovw, imported, local, keypoints):
    LOCALIZER_KINDS.add(_module.KIND.name, _module.KIND)

__all__ = [
    "LOCALIZER_KINDS",
    "KindRanks",
    "LocalizerKind",
    "LocalizerRun",
    "kind_summary",
    "options_of",
    "paired_frame_kind",
    "paired_kinds",
    "register_localizer_kind",
]

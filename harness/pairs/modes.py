"""The pairing modes' records (method §4, 13.2): ``[pairs] by`` names one, registered by its module.

A mode is its kind, its words and, where the pairs come from the frames alone, its build:
``pose`` (:mod:`.pose`), ``name`` and ``order`` (:mod:`.declared`), ``retrieval`` and
``sequence`` (:mod:`.retrieval`: the run's localizer chooses the frame). The package adds each
module's ``MODES`` in that order, the order the config's error message lists them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from harness.methods import Registry

#: The kinds of mode: by the frames' poses (method §4), declared by the user through the frames'
#: file names, or chosen by the run's localizer's descriptors (method §13.2).
KINDS = ("pose", "declared", "retrieval")


@dataclass(frozen=True)
class PairingMode:
    """One ``[pairs] by`` value: how a query frame's map frame is chosen."""

    name: str
    #: One of :data:`KINDS`.
    kind: str
    #: What a query frame's reference is, in the notes and the console (pairs without poses).
    says: str = ""
    #: ``pose`` and ``declared``: (frames, [pairs], seasons, queries, file names) -> (pairs,
    #: summary); None for ``retrieval`` (its pairs need the localizer's descriptors).
    build: Callable[..., Any] | None = None
    #: ``retrieval`` kind: the frame is chosen over ``[pairs] sequence_frames`` consecutive
    #: frames (``sequence``) rather than one.
    sequence: bool = False


PAIRING_MODES: Registry[PairingMode] = Registry("pairing mode")


def kind_of(by: str) -> str:
    """The kind of pairing mode ``by`` (``[pairs] by``)."""
    return PAIRING_MODES[by].kind

"""The pairs stage (method §4 and 13.2): each query frame's map frame.

:mod:`.config` holds ``[pairs]``; one module per pairing mode: :mod:`.pose` (the nearest viewpoint
within the heading gate), :mod:`.declared` (by name or order) and :mod:`.retrieval` (by retrieval
or sequence: the frame a localizer's descriptors retrieve), each registering its records
(:mod:`.modes`) here, in the order the config lists them; :mod:`.table` is the pair table they
share, :mod:`.keys` and :mod:`.stage` the stage's key and functions.
"""

from harness.pairs import declared, pose, retrieval
from harness.pairs.modes import PAIRING_MODES

for _module in (pose, declared, retrieval):
    for _mode in _module.MODES:
        PAIRING_MODES.add(_mode.name, _mode)

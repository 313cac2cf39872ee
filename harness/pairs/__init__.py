"""The pairs stage (SPEC sections 4 and 13.2): each query frame's map frame.

:mod:`.config` holds ``[pairs]``; one module per pairing mode: :mod:`.pose` (the nearest viewpoint
within the heading gate), :mod:`.declared` (by name or order) and :mod:`.retrieval` (by retrieval
or sequence: the frame a localizer's descriptors retrieve); :mod:`.table` is the pair table they
share, :mod:`.keys` and :mod:`.stage` the stage's key and functions.
"""

"""The pairs stage (SPEC sections 4 and 13.2): each query frame's map frame.

:mod:`.config` holds ``[pairs]``; :mod:`.build` pairs by pose (the nearest viewpoint within the
heading gate) and by name or order, and writes the pair table. Pairing by retrieval and by
sequence ranks frames, so it lives with the retrieval engines (:mod:`harness.pairs.retrieval`).
"""

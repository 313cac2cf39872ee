"""Object proposals (qBBs): the built-in proposers, the plug-in registry and the stage's build.

A user's per-image proposer: :func:`register_proposer` (``register_method``, its name before,
still works).
"""

from harness.proposals.proposers import register_method, register_proposer

__all__ = ["register_method", "register_proposer"]

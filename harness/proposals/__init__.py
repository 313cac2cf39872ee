"""Object proposals (qBBs): the built-in proposers, the plug-in registry and the stage's build.

A user's per-image proposer: :func:`register_method`.
"""

from harness.proposals.proposers import register_method

__all__ = ["register_method"]

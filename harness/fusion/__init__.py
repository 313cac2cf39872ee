"""Fusion of ranks into likelihood of change (method §5, 7 and 14).

``rules`` holds one module per rule of the catalogue, ``fuse`` the fused set, the samples
stage's build and the LoC maps. A user's rule: :func:`register_fusion_rule` (``register_method``,
its name before, still works).
"""

from harness.fusion.fuse import register_fusion_rule, register_method

__all__ = ["register_fusion_rule", "register_method"]

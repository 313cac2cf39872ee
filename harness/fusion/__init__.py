"""Fusion of ranks into likelihood of change (SPEC 5 and 14)."""

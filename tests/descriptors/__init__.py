"""Tests of ``harness.descriptors``."""

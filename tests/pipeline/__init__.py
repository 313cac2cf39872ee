"""Tests of ``harness.pipeline``."""

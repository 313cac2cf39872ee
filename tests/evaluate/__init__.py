"""Tests of ``harness.evaluate``."""

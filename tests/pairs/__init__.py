"""Tests of ``harness.pairs``."""

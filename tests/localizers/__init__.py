"""Tests of ``harness.localizers``."""

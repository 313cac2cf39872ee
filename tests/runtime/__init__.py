"""Tests of ``harness.runtime``."""

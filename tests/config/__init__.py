"""Tests of ``harness.config``."""

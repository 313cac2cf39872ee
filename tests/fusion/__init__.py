"""Tests of ``harness.fusion``."""

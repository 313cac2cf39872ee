"""Tests of ``harness.proposals``."""

"""Tests of ``harness.reports``."""

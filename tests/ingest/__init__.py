"""Tests of ``harness.ingest``."""

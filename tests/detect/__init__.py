"""Tests of ``harness.detect``."""

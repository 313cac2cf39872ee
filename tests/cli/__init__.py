"""Tests of ``harness.cli`` and of the README's commands as typed."""

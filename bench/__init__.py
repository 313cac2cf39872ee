"""Benchmarks (``make bench``). Performance is measured here, never in tests."""

"""The applications on top of the stages: ``harness reproduce`` and ``harness detect``."""

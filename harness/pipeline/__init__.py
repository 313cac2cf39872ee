"""The chain of stages: the run context, the stages, their cache keys and the runner."""

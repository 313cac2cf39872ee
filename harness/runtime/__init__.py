"""Run infrastructure: the stage cache and its collector, executors, output folders, costs."""

"""Evaluation: splits, metrics, pooled APs with intervals, SPEC 9's floor, chance and verdict."""

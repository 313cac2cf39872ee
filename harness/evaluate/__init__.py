"""Evaluation: splits, metrics, pooled APs with intervals, method §9's floor, chance and verdict."""

"""Evaluation: metrics, classic baselines, the eval/demo/bench logic and synthetic shapes."""

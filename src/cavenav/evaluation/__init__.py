"""Evaluation: sweeps over scenario x pilot x seed, their results, and reports."""

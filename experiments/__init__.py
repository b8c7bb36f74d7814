"""Experiment configs, sweeps, benchmarks and pictures."""

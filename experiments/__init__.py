"""Experiments: one config per table or figure (configs/), the pipeline that runs them, and sweeps."""

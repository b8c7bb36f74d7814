"""Experiments: one config per table or figure (configs/), the pipeline that runs them, and sweeps."""

from skillplug_jax import startup

startup.prepare_if_run_as_module()  # `python -m <this package>.x`: the allocator setting make exports

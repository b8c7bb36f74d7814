"""Benchmarks: environment, loader, training and evaluation throughput (`make bench`), each writing JSON."""

from skillplug_jax import startup

startup.prepare_if_run_as_module()  # `python -m <this package>.x`: the allocator setting make exports

"""Picture scripts: figures of the scenes and results for the README and docs."""

from skillplug_jax import startup

startup.prepare_if_run_as_module()  # `python -m <this package>.x`: the allocator setting make exports

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# Tests compile many small programs and run each briefly: XLA:CPU's backend
# optimisation costs more than it saves there (~1.5x faster test runs).
os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0")

import envs  # noqa: E402

envs.quiet_warp()

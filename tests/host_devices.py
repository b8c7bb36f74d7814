"""Run a test snippet in a fresh Python whose CPU shows as several JAX devices."""

import os
import subprocess
import sys


def run_on_host_devices(code: str, devices: int, timeout: int = 600) -> None:
  """The device count is fixed when JAX starts, hence the subprocess; the
  snippet prints OK when its own assertions pass."""
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             XLA_FLAGS=os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}")
  out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=timeout)
  assert out.returncode == 0 and "OK" in out.stdout, out.stderr[-3000:]

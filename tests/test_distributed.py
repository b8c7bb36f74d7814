"""Several hosts, tested on one machine: `skillplug pretrain --distributed` as two processes on
localhost (jax.distributed with a local coordinator, one CPU device each) writing one run
directory ends where one process with two devices does."""

import dataclasses
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from skillplug_jax import experiment
from skillplug_jax.train import checkpoint, loop, run_files
from skillplug_jax.train.scalars import read_metrics
from host_devices import run_on_host_devices
from test_train import TASKS, data_dir, leaves, tiny  # noqa: F401  (data_dir: the module fixture of synthetic demos)

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 600  # s per subprocess (each compiles the step): a hung collective fails instead of blocking CI


def pretrain_args(data_dir, workdir) -> list[str]:
  """`skillplug pretrain` arguments that build `tiny(data_dir, workdir)` (its settings as --set)."""
  def sets(cfg, base, prefix=""):
    out = []
    for f in dataclasses.fields(cfg):
      a, b = getattr(cfg, f.name), getattr(base, f.name)
      if dataclasses.is_dataclass(a):
        out += sets(a, b, f"{prefix}{f.name}.")
      elif a != b:
        out += ["--set", f"{prefix}{f.name}={','.join(map(str, a)) if isinstance(a, tuple) else a}"]
    return out
  return ["pretrain", "--config", "quick", "--policy", "skillplug", "--taskset", ",".join(TASKS),
          *sets(tiny(data_dir, workdir), experiment.preset("quick", "skillplug"))]


def free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


@pytest.mark.slow
def test_two_processes_match_two_devices(data_dir, tmp_path):
  shared, single = tmp_path / "two_processes", tmp_path / "two_devices"
  # two processes on localhost, one CPU device each, one run directory
  env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT),
         "XLA_FLAGS": os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=1"}
  port = free_port()
  procs = [subprocess.Popen(
      [sys.executable, "-m", "skillplug_jax.cli", *pretrain_args(data_dir, shared), "--distributed",
       "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)],
      env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for i in range(2)]
  try:
    # meanwhile, one process with two devices, the same command without --distributed
    run_on_host_devices(textwrap.dedent(f"""
        import jax
        from skillplug_jax import cli
        assert jax.device_count() == 2 and jax.process_count() == 1
        assert cli.main({pretrain_args(data_dir, single)!r}) == 0
        print("OK")
    """), 2, timeout=TIMEOUT)
    outs = [p.communicate(timeout=TIMEOUT)[0] for p in procs]
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
        p.wait()
  for i, (p, out) in enumerate(zip(procs, outs)):
    assert p.returncode == 0, f"process {i}:\n{out[-3000:]}"

  # the run directory: the same checkpoints, config and scalars (written once, by process 0)
  assert checkpoint.manager(shared).all_steps() == checkpoint.manager(single).all_steps() == [3, 6]
  diffs = run_files.config_differences(run_files.read_config(single), run_files.read_config(shared))
  assert [d.split(":")[0] for d in diffs] == ["workdir"]
  m2, m1 = read_metrics(shared), read_metrics(single)
  assert [r["step"] for r in m2] == [r["step"] for r in m1] == [2, 3, 4, 6]
  for a, b in zip(m2, m1):
    for k in a:
      if k.startswith("loss/") or k == "train/grad_norm":
        assert a[k] == b[k], (a["step"], k, a[k], b[k])
  assert not (shared / ".writer.lock").exists()

  # the same parameters, bit for bit: the same global batch, split the same way over two devices,
  # and the same all-reduce of two gradients
  _, a, step_a = loop.load_params(shared)
  _, b, step_b = loop.load_params(single)
  assert step_a == step_b == 6
  for x, y in zip(leaves(a), leaves(b)):
    np.testing.assert_array_equal(x, y)


def test_coordinator_needs_distributed(capsys):
  from skillplug_jax import cli
  assert cli.main(["pretrain", "--coordinator", "localhost:12355", "--process-id", "0"]) == 2
  assert "--coordinator, --process-id need --distributed" in capsys.readouterr().err

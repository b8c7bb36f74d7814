"""The soak drill (benchmarks/soak_kill.py) at a small size: a file of its own, so that pytest-xdist's
`--dist loadfile` runs it beside tests/test_preemption.py instead of after it on the same worker."""

import signal

import pytest

from test_preemption import ENV, SMALL
from test_train import data_dir  # noqa: F401  (data_dir: the module fixture of synthetic demos)


@pytest.mark.slow
def test_soak_repeated_kill_9_ends_bit_identical(data_dir, tmp_path):  # noqa: F811
  """The soak drill at a small size (benchmarks/soak_kill.py runs it at full size): killed with
  SIGKILL at random steps and once in the middle of a checkpoint write, the run still ends equal to
  an uninterrupted one, bit for bit."""
  from benchmarks import soak_kill
  overrides = ("demos=3", f"data_dir={data_dir}", *SMALL, "batch_size=4", "warmup_steps=2")
  result = soak_kill.soak(tmp_path, kills=2, steps=120, ckpt_every=10, seed=1, overrides=overrides, env=ENV,
                          log=lambda *a: None, in_process=True)
  in_save = [e for e in result["kills"] if e["kind"] == "during a checkpoint write"]
  assert in_save and in_save[0]["rc"] == -signal.SIGKILL
  random_kill = [e for e in result["kills"] if e["kind"] != "during a checkpoint write"]
  assert random_kill and random_kill[0]["rc"] == -signal.SIGKILL, result["kills"]  # it landed before the end
  assert result["final_steps"] == [120, 120]
  assert result["identical"] and result["max_abs_diff"] == 0.0, result

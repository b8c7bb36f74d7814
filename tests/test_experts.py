"""Every task's scripted expert succeeds, closed loop, through the batched env (CPU, Warp)."""

import json

import numpy as np
import pytest

import envs
from envs import rollout
from skillplug_jax import cli

EPISODES = 2  # seeded episodes per task: the 100-episode table is `make experts`


@pytest.mark.parametrize("name", list(envs.TASKS))
def test_expert_succeeds_within_the_time_limit(name):
  env = envs.make(name, num_envs=EPISODES)
  result = rollout.run_expert(env, rollout.reset_keys(0, EPISODES))
  assert not result.nan.any(), f"{name}: physics blew up"
  assert result.success.all(), f"{name}: expert failed on seeds {np.flatnonzero(~result.success)}"
  assert np.all(result.first_success_step <= env.episode_length)


def test_experts_command_writes_the_table_as_json(tmp_path, capsys):
  out = tmp_path / "experts.json"
  assert cli.main(["experts", "--taskset", "jujube_pick", "--episodes", "2", "--json", str(out)]) == 0
  table = json.loads(out.read_text())
  (row,) = table["tasks"]
  assert row["task"] == "jujube_pick" and row["episodes"] == 2
  assert row["success_rate"] == 1.0 and 0 < row["mean_steps"] <= 200
  assert "| jujube_pick | J.P. | 100.0% |" in capsys.readouterr().out


def test_experts_command_rejects_unknown_tasksets(capsys):
  assert cli.main(["experts", "--taskset", "discoverse99", "--episodes", "1"]) == 2
  assert "unknown taskset 'discoverse99'" in capsys.readouterr().err

"""Every task's scripted expert succeeds, closed loop, through the episode engine, on both backends."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import robot, rollout
from skillplug_jax import cli

EPISODES = 2  # seeded episodes per task: the 100-episode table is `make experts`
# On a CPU each MJX-Warp task compiles its own episode loop (7-30 s per task,
# about 165 s for all 11), so Warp runs a three-block stack and an articulated
# drawer here; its grasp and lift (jujube_pick) is the expert run of
# tests/test_evaluate.py's engine test. `skillplug experts --backend mjx-warp`
# runs all 11 (docs/measurements/physics_backends.md: 100% on each, 100 episodes).
WARP_TASKS = ("stack_block", "drawer_open")

CASES = ([pytest.param(name, "mujoco", id=f"{name}-mujoco") for name in envs.TASKS]
         + [pytest.param(name, "mjx-warp", id=f"{name}-mjx-warp", marks=pytest.mark.slow) for name in WARP_TASKS])


@pytest.mark.parametrize("name, backend", CASES)
def test_expert_succeeds_within_the_time_limit(name, backend):
  env = envs.make(name, num_envs=EPISODES, backend=backend)
  assert env.backend == backend
  result = rollout.run_episodes(env, rollout.expert_controller(env), rollout.reset_keys(0, EPISODES))
  assert not result.nan.any(), f"{name} on {backend}: physics blew up"
  assert result.success.all(), f"{name} on {backend}: expert failed on seeds {np.flatnonzero(~result.success)}"
  assert np.all(result.first_success_step <= env.episode_length)


@pytest.mark.parametrize("name", list(envs.TASKS))
def test_no_task_is_done_by_a_robot_at_rest(name):
  """A robot holding its home pose for the whole time limit solves nothing: no
  lid that shuts itself, no object that starts on its target (laptop_close's lid
  once crept shut in 39 of 100 such episodes)."""
  n = 12
  env = envs.make(name, num_envs=n, backend="mujoco")
  home = jnp.tile(jnp.asarray(robot.HOME_QPOS, jnp.float32), (n, 1))
  at_rest = rollout.Controller(lambda s: (), lambda w, cs, s, t: (home, cs, {}), name="at rest")
  result = rollout.run_episodes(env, at_rest, rollout.reset_keys(1000, n))
  assert result.steps_run == env.episode_length and not result.nan.any()
  assert not result.success.any(), f"{name}: solved at rest in trials {np.flatnonzero(result.success)}"


def test_experts_command_writes_the_table_as_json(tmp_path, capsys):
  out = tmp_path / "experts.json"
  assert cli.main(["experts", "--taskset", "jujube_pick", "--episodes", "2", "--backend", "mujoco",
                   "--json", str(out)]) == 0
  table = json.loads(out.read_text())
  assert table["backend"] == "mujoco"
  (row,) = table["tasks"]
  assert row["task"] == "jujube_pick" and row["episodes"] == 2
  assert row["success_rate"] == 1.0 and 0 < row["mean_steps"] <= 200
  printed = capsys.readouterr().out
  assert "| jujube_pick | J.P. | 100.0% |" in printed and "backend mujoco" in printed


def test_experts_command_rejects_unknown_tasksets(capsys):
  assert cli.main(["experts", "--taskset", "discoverse99", "--episodes", "1"]) == 2
  assert "unknown taskset 'discoverse99'" in capsys.readouterr().err


def test_experts_command_rejects_unknown_backends_naming_the_choices(capsys):
  with pytest.raises(SystemExit) as exit_info:
    cli.main(["experts", "--taskset", "jujube_pick", "--episodes", "1", "--backend", "bullet"])
  assert exit_info.value.code == 2  # argparse's usage error
  err = capsys.readouterr().err
  assert "argument --backend: invalid choice: 'bullet'" in err
  for choice in envs.env.BACKENDS:
    assert choice in err.split("choose from", 1)[1], err

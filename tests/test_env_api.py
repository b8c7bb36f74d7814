"""The batched environment API on MJX-Warp: reset, step, errors, NaN isolation, images."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import robot, rollout
from envs.env import SUCCESS_HOLD_STEPS, EnvConfig
from envs.tasks.drawer_open import DrawerOpen


@pytest.fixture(scope="module")
def stack():
  return envs.make("stack_block", num_envs=2)


def test_reset_is_deterministic_per_key(stack):
  keys = rollout.reset_keys(0, 2)
  a, b = stack.reset(keys), stack.reset(keys)
  np.testing.assert_array_equal(a.obs["object_state"], b.obs["object_state"])
  # The two episodes of a batch start apart, and another seed moves them.
  assert not np.allclose(a.obs["object_state"][0], a.obs["object_state"][1])
  c = stack.reset(rollout.reset_keys(1, 2))
  assert not np.allclose(a.obs["object_state"], c.obs["object_state"])


def test_observations_have_the_documented_shapes(stack):
  s = stack.reset(rollout.reset_keys(0, 2))
  assert s.obs["joint_pos"].shape == (2, 7)
  np.testing.assert_allclose(s.obs["joint_pos"][0], robot.HOME_QPOS, atol=1e-6)
  assert s.obs["object_state"].shape == (2, 3 * 7)
  assert "side_rgb" not in s.obs  # state-only mode renders nothing


def test_wrong_action_dimension_is_an_error_naming_the_shape(stack):
  s = stack.reset(rollout.reset_keys(0, 2))
  with pytest.raises(ValueError, match=r"actions have shape \(2, 6\), expected \(2, 7\)"):
    stack.step(s, jnp.zeros((2, 6)))
  with pytest.raises(ValueError, match="3 reset keys for 2 environments"):
    stack.reset(rollout.reset_keys(0, 3))


def test_a_nan_state_fails_its_own_episode_only(stack):
  s = stack.reset(rollout.reset_keys(0, 2))
  d = s.pipeline_state
  s = s.replace(pipeline_state=d.replace(qvel=d.qvel.at[0].set(jnp.nan)))
  action = jnp.tile(jnp.asarray(robot.HOME_QPOS, jnp.float32), (2, 1))
  s = jax.jit(stack.step)(s, action)
  np.testing.assert_array_equal(s.metrics["nan"], [1.0, 0.0])
  np.testing.assert_array_equal(s.done, [1.0, 0.0])
  assert np.all(np.isfinite(s.pipeline_state.qpos[1]))


def test_rendered_observations_show_the_scene_from_both_cameras():
  env = envs.make("kiwi_place", num_envs=2, render=True, image_size=(24, 32))  # (H, W)
  s = env.reset(rollout.reset_keys(0, 2))
  side, wrist = np.asarray(s.obs["side_rgb"]), np.asarray(s.obs["wrist_rgb"])
  assert side.shape == wrist.shape == (2, 24, 32, 3) and side.dtype == np.uint8
  assert side.std() > 5 and wrist.std() > 5  # not blank
  assert not np.array_equal(side, wrist)
  assert not np.array_equal(side[0], side[1])  # the objects moved between episodes
  s = jax.jit(env.step)(s, s.obs["joint_pos"])  # images come back after every step too
  assert s.obs["side_rgb"].shape == (2, 24, 32, 3)
  jax.effects_barrier()  # finish Warp's render calls while their context is alive


class _Scripted(DrawerOpen):
  """The drawer task with a predicate that holds on chosen control steps only."""
  holds_on = frozenset(range(3, 12)) | frozenset(range(14, 40))  # 9 steps, a break, then 26

  def success(self, data):
    step = jnp.round(data.time / self.config.control_dt).astype(jnp.int32)
    return jnp.isin(step, jnp.asarray(sorted(self.holds_on)))


def test_success_is_declared_after_the_predicate_held_for_half_a_second():
  """A run of 9 steps (an object passing through its target) is not a success;
  the next run is, declared after 10 steps, and dated from the run's first step."""
  assert SUCCESS_HOLD_STEPS == 10
  benv = envs.batched.BatchedEnv(_Scripted(EnvConfig(num_envs=1)), 1)
  s = benv.reset(rollout.reset_keys(0, 1))
  step = jax.jit(benv.step)
  action = jnp.asarray(robot.HOME_QPOS, jnp.float32)[None]
  done_at = None
  for t in range(1, 30):
    s = step(s, action)
    if done_at is None and float(s.done[0]) > 0:
      done_at = t
  assert done_at == 14 + SUCCESS_HOLD_STEPS - 1
  assert int(s.info["first_success_step"][0]) == 14
  assert float(s.metrics["success"][0]) == 1.0

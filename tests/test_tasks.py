"""Task logic: registry, reset sampling, success checks (hand-placed states), IK."""

import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import envs
from envs import robot
from envs.env import EnvConfig
from envs.tasks.stack_block import separated_positions


def test_registry_holds_the_eleven_tasks_in_two_tasksets():
  assert len(envs.TASKS) == 11
  assert len(envs.TASKSETS["discoverse7"]) == 7
  assert len(envs.TASKSETS["discoverse_fewshot4"]) == 4
  assert set(envs.TASKSETS["discoverse7"]) | set(envs.TASKSETS["discoverse_fewshot4"]) == set(envs.TASKS)


def test_unknown_names_are_rejected_with_the_valid_ones_listed():
  with pytest.raises(ValueError, match="unknown task 'pick_banana'.*jujube_pick"):
    envs.make("pick_banana")
  with pytest.raises(ValueError, match="unknown taskset 'discoverse8'.*discoverse7"):
    envs.taskset("discoverse8")
  assert envs.taskset("mouse_push") == ("mouse_push",)


def _quat(axis, angle):
  axis = np.asarray(axis, float) / np.linalg.norm(axis)
  return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def _data(env, poses=(), joints=(), qpos=None):
  """Kinematics of a hand-placed state (free bodies at `poses`, joints at values),
  with the mjx.Data fields that success checks read."""
  m = env.mj_model
  d = mujoco.MjData(m)
  d.qpos[:] = m.qpos0 if qpos is None else qpos
  d.qpos[:6] = robot.HOME_QPOS[:6]
  for body, xyz, *quat in poses:
    a = env._qadr[body]
    d.qpos[a:a + 3] = xyz
    d.qpos[a + 3:a + 7] = quat[0] if quat else (1, 0, 0, 0)
  for joint, value in joints:
    d.qpos[env._qadr[joint]] = value
  mujoco.mj_kinematics(m, d)
  return SimpleNamespace(qpos=jnp.asarray(d.qpos), xpos=jnp.asarray(d.xpos),
                         xmat=jnp.asarray(d.xmat).reshape(-1, 3, 3), xquat=jnp.asarray(d.xquat),
                         site_xpos=jnp.asarray(d.site_xpos), geom_xpos=jnp.asarray(d.geom_xpos))


def _home_grasp(env):
  return np.asarray(_data(env).site_xpos[env._site["grasp"]])


TILT = _quat((1, 0, 0), math.radians(10))  # beyond DISCOVERSE's ~8 degree 'upright'

# task -> (succeeding placements, [near misses]); each a (poses, joints) pair.
CASES = {
    "kiwi_place": (
        ([("bowl", (0.3, 0.1, 0)), ("kiwi", (0.31, 0.1, 0.03))], []),
        [([("bowl", (0.3, 0.1, 0)), ("kiwi", (0.323, 0.1, 0.03))], []),
         ([("bowl", (0.3, 0.1, 0), TILT), ("kiwi", (0.3, 0.1, 0.03))], [])]),
    "stack_block": (
        ([("blue", (0.3, 0, 0.015)), ("green", (0.31, 0, 0.045)), ("red", (0.29, 0.005, 0.075))], []),
        [([("blue", (0.3, 0, 0.015)), ("green", (0.31, 0, 0.045)), ("red", (0.3, 0.023, 0.075))], []),
         ([("blue", (0.3, 0, 0.015), TILT), ("green", (0.3, 0, 0.045)), ("red", (0.3, 0, 0.075))], [])]),
    "coffeecup_place": (
        ([("plate", (0.3, 0.1, 0)), ("cup", (0.31, 0.1, 0.006))], []),
        [([("plate", (0.3, 0.1, 0)), ("cup", (0.3, 0.123, 0.006))], []),
         ([("plate", (0.3, 0.1, 0)), ("cup", (0.3, 0.1, 0.006), TILT)], [])]),
    "block_bridge_place": (
        ([("bridge1", (0.3, 0, 0.015)), ("bridge2", (0.33, 0.001, 0.015)),
          ("green", (0.315, -0.02, 0.04)), ("purple", (0.315, 0.02, 0.04))], []),
        [([("bridge1", (0.3, 0, 0.015)), ("bridge2", (0.3335, 0, 0.015)),
           ("green", (0.315, -0.02, 0.04)), ("purple", (0.315, 0.02, 0.04))], []),
         ([("bridge1", (0.3, 0, 0.015)), ("bridge2", (0.33, 0, 0.015)),
           ("green", (0.315, -0.02, 0.04)), ("purple", (0.315, 0.1, 0.01))], []),
         ([("bridge1", (0.3, 0, 0.015)), ("bridge2", (0.33, 0, 0.015)),
           ("green", (0.315, -0.02, 0.05), _quat((0, 1, 0), math.pi / 2)), ("purple", (0.315, 0.02, 0.04))], [])]),
    "drawer_open": (([], [("drawer", 0.16)]), [([], [("drawer", 0.14)])]),
    "laptop_close": (([], [("lid", 0.05)]), [([], [("lid", 0.15)])]),
    "cuplid_cover": (
        ([("plate", (0.3, 0.1, 0)), ("cup", (0.31, 0.1, 0.006)), ("lid", (0.32, 0.1, 0.08))], []),
        [([("plate", (0.3, 0.1, 0)), ("cup", (0.31, 0.1, 0.006)), ("lid", (0.335, 0.1, 0.08))], []),
         ([("plate", (0.3, 0.1, 0)), ("cup", (0.325, 0.1, 0.006)), ("lid", (0.325, 0.1, 0.08))], [])]),
    "block_place": (
        ([("bowl", (0.3, 0.1, 0)), ("block", (0.3, 0.115, 0.02))], []),
        [([("bowl", (0.3, 0.1, 0)), ("block", (0.3, 0.124, 0.02))], []),
         ([("bowl", (0.3, 0.1, 0), TILT), ("block", (0.3, 0.1, 0.02))], [])]),
    "jujube_place": (
        ([("cup", (0.3, 0.1, 0)), ("jujube", (0.31, 0.11, 0.02))], []),
        [([("cup", (0.3, 0.1, 0)), ("jujube", (0.316, 0.116, 0.02))], []),
         ([("cup", (0.3, 0.1, 0), TILT), ("jujube", (0.3, 0.1, 0.02))], [])]),
    "mouse_push": (
        ([("pad", (0.38, 0, 0)), ("mouse", (0.35, 0.0, 0.015))], []),
        [([("pad", (0.38, 0, 0)), ("mouse", (0.38, 0.042, 0.015))], [])]),
}


@pytest.fixture(scope="module")
def task_envs():
  return {name: cls(EnvConfig()) for name, cls in envs.TASKS.items()}


@pytest.mark.parametrize("name", sorted(CASES))
def test_success_accepts_hand_placed_success_and_rejects_near_misses(task_envs, name):
  env = task_envs[name]
  good, misses = CASES[name]
  assert bool(env.success(_data(env, *good))), f"{name}: succeeding state rejected"
  for i, miss in enumerate(misses):
    assert not bool(env.success(_data(env, *miss))), f"{name}: near miss {i} accepted"


def test_jujube_pick_success_is_distance_to_the_grasp_point(task_envs):
  env = task_envs["jujube_pick"]
  g = _home_grasp(env)
  assert bool(env.success(_data(env, [("jujube", g + [0.02, 0.0, 0.0])])))
  assert not bool(env.success(_data(env, [("jujube", g + [0.0, 0.033, 0.0])])))


@pytest.mark.parametrize("name", sorted(envs.TASKS))
def test_sampled_initial_states_fail_the_success_check(task_envs, name):
  env = task_envs[name]
  for seed in range(5):
    qpos = np.asarray(env.sample_objects(jax.random.PRNGKey(seed), jnp.asarray(env.mj_model.qpos0)))
    assert not bool(env.success(_data(env, qpos=qpos))), f"{name}: seed {seed} starts solved"


@pytest.mark.parametrize("name", sorted(envs.TASKS))
def test_reset_sampling_is_a_function_of_the_key(task_envs, name):
  env = task_envs[name]
  q0 = jnp.asarray(env.mj_model.qpos0)
  a = env.sample_objects(jax.random.PRNGKey(1), q0)
  b = env.sample_objects(jax.random.PRNGKey(1), q0)
  c = env.sample_objects(jax.random.PRNGKey(2), q0)
  np.testing.assert_array_equal(a, b)
  if name != "drawer_open":  # the only task without randomisation
    assert not np.allclose(a, c)


def test_ik_puts_the_grasp_point_on_target_for_down_and_forward_tools(task_envs):
  env = task_envs["jujube_pick"]
  m = env.mj_model
  d = mujoco.MjData(m)
  rng = np.random.default_rng(0)
  for _ in range(20):
    p = np.array([rng.uniform(0.2, 0.45), rng.uniform(-0.2, 0.2), rng.uniform(0.01, 0.15)])
    yaw = rng.uniform(-np.pi, np.pi)
    for pitch in (robot.TOOL_DOWN, robot.TOOL_FORWARD):
      q = np.asarray(robot.grasp_joint_targets(jnp.asarray(p), yaw, pitch))
      d.qpos[:6] = q[:6]
      mujoco.mj_kinematics(m, d)
      np.testing.assert_allclose(d.site_xpos[env._site["grasp"]], p, atol=1e-4)
      rot = d.site_xmat[env._site["grasp"]].reshape(3, 3)
      if pitch == robot.TOOL_DOWN:
        np.testing.assert_allclose(rot[:, 2], [0, 0, -1], atol=1e-4)
        closing = np.arctan2(rot[1, 1], rot[0, 1])  # finger axis, up to a half turn
        assert abs(np.sin(closing - yaw)) < 1e-3
      else:
        assert rot[2, 2] == pytest.approx(0.0, abs=1e-4)


def test_separated_positions_keeps_every_pair_apart():
  nominal = jnp.array([[0.26, -0.1], [0.36, 0.0], [0.26, 0.1]])
  for seed in range(20):
    xy = np.asarray(separated_positions(jax.random.PRNGKey(seed), nominal, (0.08, 0.06), 0.07))
    assert np.all(np.abs(xy - nominal) <= np.array([0.08, 0.06]) + 1e-6)
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(3)
    assert d.min() >= 0.07 - 1e-6

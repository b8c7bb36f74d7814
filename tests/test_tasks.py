"""Task logic: registry, reset sampling, success checks (hand-placed states), IK.

Task logic is backend-agnostic (pure functions of the state arrays), so it is
checked on environments made for MuJoCo's C engine, which need no MJX model.
"""

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


@pytest.mark.parametrize("name", sorted(envs.TASKS))
def test_every_task_fits_the_declared_object_state_width(task_envs, name):
  env = task_envs[name]
  width = env.observation_size["object_state"]
  assert 0 < width <= envs.OBJECT_STATE_DIM
  obs = env.observation(_data(env))
  assert obs["object_state"].shape == (width,)
  assert envs.padded_object_state(obs["object_state"][None]).shape == (1, envs.OBJECT_STATE_DIM)


def test_unknown_names_are_rejected_with_the_valid_ones_listed():
  with pytest.raises(ValueError, match="unknown task 'pick_banana'.*jujube_pick"):
    envs.make("pick_banana")
  with pytest.raises(ValueError, match="unknown taskset 'discoverse8'.*discoverse7"):
    envs.taskset("discoverse8")
  assert envs.taskset("mouse_push") == ("mouse_push",)
  with pytest.raises(ValueError, match="unknown backend 'bullet'; valid backends: auto, mujoco, mjx-warp"):
    envs.TASKS["mouse_push"](EnvConfig(backend="bullet"))


def _quat(axis, angle):
  axis = np.asarray(axis, float) / np.linalg.norm(axis)
  return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def _data(env, poses=(), joints=(), qpos=None, arm=None):
  """A hand-placed state (free bodies at `poses`, joints at values, the arm at
  home or at the 7-D joint targets `arm`), through MuJoCo's forward pass, with
  the mjx.Data fields that success checks read (contact sensors included)."""
  m = env.mj_model
  d = mujoco.MjData(m)
  d.qpos[:] = m.qpos0 if qpos is None else qpos
  q = robot.HOME_QPOS if arm is None else np.asarray(arm)
  d.qpos[:6] = q[:6]
  d.qpos[6:8] = q[6]  # both fingers open by the 7th value
  for body, xyz, *quat in poses:
    a = env._qadr[body]
    d.qpos[a:a + 3] = xyz
    d.qpos[a + 3:a + 7] = quat[0] if quat else (1, 0, 0, 0)
  for joint, value in joints:
    d.qpos[env._qadr[joint]] = value
  mujoco.mj_forward(m, d)
  return SimpleNamespace(qpos=jnp.asarray(d.qpos), xpos=jnp.asarray(d.xpos),
                         xmat=jnp.asarray(d.xmat).reshape(-1, 3, 3), xquat=jnp.asarray(d.xquat),
                         site_xpos=jnp.asarray(d.site_xpos), geom_xpos=jnp.asarray(d.geom_xpos),
                         sensordata=jnp.asarray(d.sensordata))


def _closed_on(xyz, dz=0.0):
  """Arm joint targets with the closed fingers at `xyz` (+dz): the gripper holds what is there."""
  p = np.asarray(xyz, float) + [0.0, 0.0, dz]
  return np.asarray(robot.grasp_joint_targets(jnp.asarray(p), 0.0, robot.TOOL_DOWN, robot.GRIPPER_CLOSED))


TILT = _quat((1, 0, 0), math.radians(10))  # beyond DISCOVERSE's ~8 degree 'upright'
# Resting heights of the cases below: kiwi in a bowl 0.006 + 0.021, block in a
# bowl 0.006 + 0.015, jujube in a cup 0.005 + 0.012, cup on a plate 0.006,
# lid on a cup 0.07, blocks on blocks 0.03, bridge blocks 0.025 above the pieces.

# task -> (succeeding placements, [near misses]); each a (poses, joints) pair.
CASES = {
    "kiwi_place": (
        ([("bowl", (0.3, 0.1, 0)), ("kiwi", (0.31, 0.1, 0.027))], []),
        [([("bowl", (0.3, 0.1, 0)), ("kiwi", (0.323, 0.1, 0.027))], []),
         ([("bowl", (0.3, 0.1, 0), TILT), ("kiwi", (0.3, 0.1, 0.027))], [])]),
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
        ([("plate", (0.3, 0.1, 0)), ("cup", (0.31, 0.1, 0.006)), ("lid", (0.32, 0.1, 0.076))], []),
        [([("plate", (0.3, 0.1, 0)), ("cup", (0.31, 0.1, 0.006)), ("lid", (0.335, 0.1, 0.08))], []),
         ([("plate", (0.3, 0.1, 0)), ("cup", (0.325, 0.1, 0.006)), ("lid", (0.325, 0.1, 0.08))], [])]),
    "block_place": (
        ([("bowl", (0.3, 0.1, 0)), ("block", (0.3, 0.115, 0.021))], []),
        [([("bowl", (0.3, 0.1, 0)), ("block", (0.3, 0.124, 0.02))], []),
         ([("bowl", (0.3, 0.1, 0), TILT), ("block", (0.3, 0.1, 0.02))], [])]),
    "jujube_place": (
        ([("cup", (0.3, 0.1, 0)), ("jujube", (0.31, 0.11, 0.017))], []),
        [([("cup", (0.3, 0.1, 0)), ("jujube", (0.316, 0.116, 0.02))], []),
         ([("cup", (0.3, 0.1, 0), TILT), ("jujube", (0.3, 0.1, 0.02))], [])]),
    "mouse_push": (
        ([("pad", (0.38, 0, 0)), ("mouse", (0.35, 0.0, 0.015))], []),
        [([("pad", (0.38, 0, 0)), ("mouse", (0.38, 0.042, 0.015))], [])]),
}


@pytest.fixture(scope="module")
def task_envs():
  return {name: cls(EnvConfig(backend="mujoco")) for name, cls in envs.TASKS.items()}


@pytest.mark.parametrize("name", sorted(CASES))
def test_success_accepts_hand_placed_success_and_rejects_near_misses(task_envs, name):
  env = task_envs[name]
  good, misses = CASES[name]
  assert bool(env.success(_data(env, *good))), f"{name}: succeeding state rejected"
  for i, miss in enumerate(misses):
    assert not bool(env.success(_data(env, *miss))), f"{name}: near miss {i} accepted"


# The object a place/stack/cover task moves last, and the part of the
# success state that is "on its target".
MOVED = {"kiwi_place": "kiwi", "stack_block": "red", "coffeecup_place": "cup", "block_bridge_place": "purple",
         "cuplid_cover": "lid", "block_place": "block", "jujube_place": "jujube"}


def _moved(poses, body, dz):
  return [(b, tuple(np.add(xyz, (0, 0, dz))), *q) if b == body else (b, xyz, *q) for b, xyz, *q in poses]


@pytest.mark.parametrize("name", sorted(MOVED))
def test_placement_needs_the_object_resting_and_released(task_envs, name):
  """Hovering above the target, carried to it or still held on it is not done."""
  env = task_envs[name]
  (poses, joints), _ = CASES[name]
  body = MOVED[name]
  at = dict((b, xyz) for b, xyz, *_ in poses)[body]
  assert bool(env.success(_data(env, poses, joints))), "resting, released: accepted"
  hovering = _moved(poses, body, 0.03)
  assert not bool(env.success(_data(env, hovering, joints))), "3 cm above its target, gripper away"
  carried = _data(env, hovering, joints, arm=_closed_on(at, 0.03))
  assert not bool(env.success(carried)), "carried 3 cm above its target"
  held = _data(env, poses, joints, arm=_closed_on(at))
  assert float(held.sensordata.sum()) > 0, "the closed fingers touch the object"
  assert not bool(env.success(held)), "resting on its target but still in the fingers"


def test_jujube_pick_needs_the_jujube_lifted_at_the_grasp_point(task_envs):
  env = task_envs["jujube_pick"]
  on_table = (0.3, 0.05, 0.012)
  reach = _data(env, [("jujube", on_table)], arm=_closed_on(on_table))
  assert not bool(env.success(reach)), "grasped but not lifted"
  open_reach = _data(env, [("jujube", on_table)],
                     arm=np.asarray(robot.grasp_joint_targets(jnp.asarray(on_table), 0.0)))
  assert not bool(env.success(open_reach)), "the open gripper around a jujube on the table"
  lifted = (0.3, 0.05, 0.012 + 0.035)
  arm = _closed_on(lifted)
  g = np.asarray(_data(env, arm=arm).site_xpos[env._site["grasp"]])
  assert bool(env.success(_data(env, [("jujube", g + [0.0, 0.0, 0.0])], arm=arm))), "lifted in the fingers"
  assert not bool(env.success(_data(env, [("jujube", g + [0.0, 0.033, 0.0])], arm=arm))), "3.3 cm away"
  arm = _closed_on(on_table, 0.02)
  g = np.asarray(_data(env, arm=arm).site_xpos[env._site["grasp"]])
  assert not bool(env.success(_data(env, [("jujube", g)], arm=arm))), "in the fingers, only 2 cm up"


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

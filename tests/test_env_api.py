"""The batched environment API on both backends: reset, step, errors, backend
names, identical resets, failure isolation, images, the success hold.

Most tests run on MuJoCo's C engine ("mujoco", fast on a CPU); MJX-Warp keeps
its own NaN isolation and render tests, and meets the C engine in the reset
comparison over every task.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import robot, rollout
from envs.env import SUCCESS_HOLD_STEPS, EnvConfig
from envs.mujoco_batch import MujocoBatchEnv, PhysicsState
from envs.tasks.drawer_open import DrawerOpen

HOME = jnp.tile(jnp.asarray(robot.HOME_QPOS, jnp.float32), (2, 1))


@pytest.fixture(scope="module")
def stack():
  return envs.make("stack_block", num_envs=2, backend="mujoco")


@pytest.fixture(scope="module")
def warp_stack():
  return envs.make("stack_block", num_envs=2, backend="mjx-warp")


def test_reset_is_deterministic_per_key(stack):
  keys = rollout.reset_keys(0, 2)
  a = stack.reset(keys)
  stack.step(a, HOME)  # the C batch holds the physics: a reset must start it afresh
  b = stack.reset(keys)
  np.testing.assert_array_equal(a.obs["object_state"], b.obs["object_state"])
  np.testing.assert_array_equal(a.pipeline_state.qvel, b.pipeline_state.qvel)
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
  assert isinstance(s.pipeline_state, PhysicsState)
  assert s.pipeline_state.qpos.dtype == jnp.float32
  assert s.pipeline_state.xmat.shape == (2, stack.env.mj_model.nbody, 3, 3)


@pytest.mark.parametrize("fixture", ["stack", "warp_stack"])
def test_wrong_action_dimension_is_an_error_naming_the_shape(request, fixture):
  benv = request.getfixturevalue(fixture)
  with pytest.raises(ValueError, match="3 reset keys for 2 environments"):
    benv.reset(rollout.reset_keys(0, 3))
  keys = rollout.reset_keys(0, 2)
  s = benv.reset(keys) if benv.backend == "mujoco" else jax.eval_shape(benv.reset, keys)
  with pytest.raises(ValueError, match=r"actions have shape \(2, 6\), expected \(2, 7\)"):
    benv.step(s, jnp.zeros((2, 6)))


def test_auto_is_resolved_at_the_edges_and_rejected_below_them():
  """'auto' is resolved where a command or API call starts (envs.make, DemoConfig, ...); a layer
  below is handed the concrete name and rejects 'auto', naming itself."""
  from skillplug_jax.data.demos import DemoConfig
  resolved = envs.resolve_backend("auto")
  assert resolved in envs.ENGINES and DemoConfig(backend="auto").backend == resolved
  assert DemoConfig(backend="auto").name.endswith(f"_{resolved}")
  with pytest.raises(envs.UnresolvedBackend, match=r"DrawerOpen\(EnvConfig\(backend=...\)\) takes a resolved backend"):
    DrawerOpen(EnvConfig(backend="auto"))
  with pytest.raises(envs.UnresolvedBackend, match=r"envs.renderer_of takes a resolved backend"):
    envs.renderer_of("auto")
  with pytest.raises(ValueError, match="unknown backend 'bullet'"):
    envs.renderer_of("bullet")
  assert envs.renderer_of("mujoco") == "mujoco-opengl"
  assert issubclass(envs.UnresolvedBackend, ValueError)  # the CLI's one-line error


def test_backend_names_are_checked_and_auto_follows_the_platform(stack, warp_stack):
  with pytest.raises(ValueError, match="unknown backend 'bullet'; valid backends: auto, mujoco, mjx-warp"):
    envs.make("stack_block", backend="bullet")
  expected = "mjx-warp" if jax.default_backend() == "gpu" else "mujoco"
  assert envs.resolve_backend("auto") == expected
  assert envs.make("drawer_open").backend == expected
  assert stack.backend == stack.env.backend == "mujoco"
  assert warp_stack.backend == warp_stack.env.backend == "mjx-warp"
  with pytest.raises(ValueError, match="needs an environment made for the 'mujoco' backend"):
    MujocoBatchEnv(warp_stack.env, 2)
  with pytest.raises(ValueError, match="BatchedEnv runs MJX-Warp"):
    envs.batched.BatchedEnv(stack.env, 2)


@pytest.mark.slow
def test_both_backends_reset_every_task_to_the_same_state():
  """Same reset keys, same start: the sampler's qpos exactly, and what the
  forward pass derives from it (observations, poses) to float32 rounding."""
  keys = rollout.reset_keys(3, 2)
  for name in envs.TASKS:
    c = envs.make(name, num_envs=2, backend="mujoco").reset(keys)
    w = jax.jit(envs.make(name, num_envs=2, backend="mjx-warp").reset)(keys)
    np.testing.assert_array_equal(c.pipeline_state.qpos, w.pipeline_state.qpos, err_msg=name)
    assert set(c.obs) == set(w.obs) == {"joint_pos", "object_state"}
    for k in c.obs:
      np.testing.assert_allclose(c.obs[k], w.obs[k], rtol=0, atol=1e-6, err_msg=f"{name}: {k}")
    for f in ("qvel", "xpos", "xquat", "xmat", "site_xpos", "geom_xpos", "sensordata"):
      np.testing.assert_allclose(getattr(c.pipeline_state, f), getattr(w.pipeline_state, f),
                                 rtol=0, atol=1e-6, err_msg=f"{name}: {f}")
    # The bookkeeping (done, metrics, step counters) starts the same.
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(a, b, err_msg=name),
                 (c.done, c.reward, c.metrics, c.info), (w.done, w.reward, w.metrics, w.info))


@pytest.mark.slow
def test_a_nan_state_fails_its_own_episode_only_on_warp(warp_stack):
  s = warp_stack.reset(rollout.reset_keys(0, 2))
  d = s.pipeline_state
  s = s.replace(pipeline_state=d.replace(qvel=d.qvel.at[0].set(jnp.nan)))
  s = jax.jit(warp_stack.step)(s, HOME)
  np.testing.assert_array_equal(s.metrics["nan"], [1.0, 0.0])
  np.testing.assert_array_equal(s.done, [1.0, 0.0])
  assert np.all(np.isfinite(s.pipeline_state.qpos[1]))


@pytest.mark.parametrize("poison", [np.nan, 1e12], ids=["nan_qvel", "huge_finite_qvel"])
def test_a_c_engine_failure_fails_its_own_episode_only(stack, poison, capfd):
  """Env 0's velocities are poisoned in the C batch before its 2nd step: a NaN
  (caught as non-finite), or a huge finite value, which MuJoCo answers with a
  warning and a reset of that simulation (caught by its clock going back).
  Env 0 fails alone and keeps its last good state; env 1 runs as if nothing happened."""
  keys = rollout.reset_keys(0, 2)
  ref = [stack.reset(keys)]
  for _ in range(3):
    ref.append(stack.step(ref[-1], HOME))

  s = stack.step(stack.reset(keys), HOME)
  good_qpos = stack._saved["qpos"].copy()
  stack._saved["qvel"][0] = poison
  capfd.readouterr()
  s1 = stack.step(s, HOME)
  assert "simulation is unstable" in "".join(capfd.readouterr())  # MuJoCo's warning
  np.testing.assert_array_equal(s1.metrics["nan"], [1.0, 0.0])
  np.testing.assert_array_equal(s1.done, [1.0, 0.0])
  assert float(s1.metrics["success"][0]) == 0.0
  # Env 0 keeps its last good state, in the State and in the C batch.
  np.testing.assert_array_equal(s1.pipeline_state.qpos[0], s.pipeline_state.qpos[0])
  np.testing.assert_array_equal(s1.obs["object_state"][0], s.obs["object_state"][0])
  np.testing.assert_array_equal(stack._saved["qpos"][0], good_qpos[0])
  # Env 1 matches the unpoisoned run, now and after a further step, while env 0 stays put.
  s2 = stack.step(s1, HOME)
  for got, want in ((s1, ref[2]), (s2, ref[3])):
    for f in ("qpos", "qvel", "xpos"):
      np.testing.assert_array_equal(getattr(got.pipeline_state, f)[1], getattr(want.pipeline_state, f)[1], err_msg=f)
    for k in got.obs:
      np.testing.assert_array_equal(got.obs[k][1], want.obs[k][1], err_msg=k)
    assert float(got.done[1]) == float(got.metrics["nan"][1]) == 0.0
  np.testing.assert_array_equal(s2.pipeline_state.qpos[0], s.pipeline_state.qpos[0])
  np.testing.assert_array_equal(s2.metrics["nan"], [1.0, 0.0])


@pytest.mark.parametrize("backend", ["mujoco", pytest.param("mjx-warp", marks=pytest.mark.slow)])
def test_rendered_observations_show_the_scene_from_both_cameras(backend):
  """Both cameras, at a non-square (H, W); MuJoCo's OpenGL renderer (EGL) on the
  C engine, Warp's ray caster on MJX-Warp."""
  env = envs.make("kiwi_place", num_envs=2, backend=backend, render=True, image_size=(24, 32))
  s = env.reset(rollout.reset_keys(0, 2))
  side, wrist = np.asarray(s.obs["side_rgb"]), np.asarray(s.obs["wrist_rgb"])
  assert side.shape == wrist.shape == (2, 24, 32, 3) and side.dtype == wrist.dtype == np.uint8
  for i in range(2):
    assert side[i].std() > 5 and wrist[i].std() > 5  # not blank
  assert not np.array_equal(side, wrist)
  assert not np.array_equal(side[0], side[1])  # the objects moved between episodes
  step = env.step if backend == "mujoco" else jax.jit(env.step)
  s = step(s, s.obs["joint_pos"])  # images come back after every step too
  assert s.obs["side_rgb"].shape == s.obs["wrist_rgb"].shape == (2, 24, 32, 3)
  assert np.asarray(s.obs["wrist_rgb"]).std() > 5
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
  benv = envs.batch_of(_Scripted(EnvConfig(backend="mujoco", num_envs=1)), 1)
  s = benv.reset(rollout.reset_keys(0, 1))
  action = jnp.asarray(robot.HOME_QPOS, jnp.float32)[None]
  done_at = None
  for t in range(1, 30):
    s = benv.step(s, action)
    if done_at is None and float(s.done[0]) > 0:
      done_at = t
  assert done_at == 14 + SUCCESS_HOLD_STEPS - 1
  assert int(s.info["first_success_step"][0]) == 14
  assert float(s.metrics["success"][0]) == 1.0

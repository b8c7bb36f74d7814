"""LIBERO on our C-engine batch (envs/libero/engine.py, controller.py), judged by LIBERO's own
environment: from the same benchmark init state under the same actions, our joint positions and
velocities (arm, fingers and every object) and observations after each control step against
OffScreenRenderEnv's, and both cameras pixel for pixel;
the goal predicate against its `_check_success` on those rollout states; a controller that
departs from robosuite's (a gain 1% off, the first step's cached reading ignored) caught by the
same tolerance; a batch of B the same as B runs alone.

The reference steps with its cameras off (they do not touch the physics; 0.15-0.3 s a control
step instead of 0.7-0.9 s). One task per suite by default; every task with `-m sweep`.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from envs.libero import controller as osc
from envs.libero import engine, predicates, scene, suites

FOUR = ("libero_spatial", "libero_object", "libero_goal", "libero_10")
DEFAULT = (("libero_spatial", 4), ("libero_object", 0), ("libero_goal", 5), ("libero_10", 2))
SWEEP = tuple((s, i) for s in FOUR for i in range(10) if (s, i) not in DEFAULT)
STEPS = 24  # control steps per rollout (1.2 s)
# One trial per reference env: a LIBERO reset re-samples the fixtures' placement (docs/libero.md),
# so only a fresh env, seeded as the scene was built, has our scene's model.
def trial(index: int) -> int:
  return (7 * index) % suites.INIT_STATES_PER_TASK
QPOS_TOL = 1e-6  # rad or m, over the whole rollout
QVEL_TOL = 1e-4


def actions(steps: int, seed: int) -> np.ndarray:
  """A smooth arm motion that turns the hand and closes then opens the gripper; some steps with an
  exactly zero rotation (robosuite then keeps its previous goal orientation)."""
  t = np.arange(steps)[:, None]
  phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, (1, 6))
  amplitude = np.array([[0.8, 0.8, 0.6, 0.3, 0.3, 0.4]])
  arm = amplitude * np.sin(t / 4.0 + phase)
  arm[t[:, 0] % 5 == 0, 3:] = 0.0
  grip = np.where((t[:, 0] // 8) % 2 == 1, 1.0, -1.0)[:, None]
  return np.concatenate([arm, grip], axis=1)


@dataclasses.dataclass
class Reference:
  suite: str
  index: int
  scene: scene.Scene
  states: np.ndarray  # [1, 1 + nq + nv]
  actions: np.ndarray  # [1, steps, 7]
  qpos: np.ndarray  # [1, steps, nq] after each control step
  qvel: np.ndarray
  success: np.ndarray  # [1, steps] the reference's _check_success
  observed: np.ndarray  # [1, steps, 3 + 3 + 7 + 2] eef pos, first object's pos, joints, fingers


@functools.lru_cache(maxsize=None)
def record(suite: str, index: int) -> Reference:
  env = scene.reference_env(suite, index)
  try:
    for cam in scene.CAMERAS:
      env.env.modify_observable(f"{cam}_image", "enabled", False)
    s = scene.cached(suite, index) or scene.build_scene(suite, index, env=env)
    states = suites.init_states(suite, index)[[trial(index)]]
    acts = actions(STEPS, index)[None]
    env.set_init_state(states[0])
    qpos, qvel, success, observed = [], [], [], []
    for a in acts[0]:
      obs = env.step(a)[0]
      qpos.append(env.env.sim.data.qpos.copy())
      qvel.append(env.env.sim.data.qvel.copy())
      success.append(bool(env.check_success()))
      observed.append(observed_vector(obs, s))
    return Reference(suite, index, s, states, acts, np.array(qpos)[None], np.array(qvel)[None],
                     np.array(success)[None], np.array(observed)[None])
  finally:
    env.close()


def first_object(s: scene.Scene) -> str:
  return next(name for name, o in s.meta["objects"].items() if o["kind"] == "object")


def observed_vector(obs: dict, s: scene.Scene) -> np.ndarray:
  """Some of LIBERO's observations of one env (or [B] envs), in a row."""
  names = ("robot0_eef_pos", f"{first_object(s)}_pos", "robot0_joint_pos", "robot0_gripper_qpos")
  return np.concatenate([np.asarray(obs[n]) for n in names], axis=-1)


def rollout(s: scene.Scene, states: np.ndarray, acts: np.ndarray, batch_cls=engine.LiberoBatch):
  """(qpos, qvel, success, observations) [B, steps, ...] of our engine."""
  b = batch_cls(s, len(states), nthread=1)
  b.reset(states)
  qpos, qvel, success, observed = [], [], [], []
  for k in range(acts.shape[1]):
    b.step(acts[:, k])
    qpos.append(b.data["qpos"].copy()), qvel.append(b.data["qvel"].copy())
    success.append(b.success())
    observed.append(observed_vector(b.observe(), s))
  return np.stack(qpos, 1), np.stack(qvel, 1), np.stack(success, 1), np.stack(observed, 1)


def errors(ref: Reference, qpos: np.ndarray, qvel: np.ndarray) -> tuple[float, float]:
  return float(np.abs(qpos - ref.qpos).max()), float(np.abs(qvel - ref.qvel).max())


def check_parity(ref: Reference) -> None:
  qpos, qvel, success, observed = rollout(ref.scene, ref.states, ref.actions)
  dq, dv = errors(ref, qpos, qvel)
  assert np.abs(observed - ref.observed).max() < QPOS_TOL, (ref.suite, ref.index, np.abs(observed - ref.observed).max())
  print(f"{ref.suite} {ref.index}: max |qpos - ref| {dq:.2e}, |qvel - ref| {dv:.2e} over {STEPS} steps from init state {trial(ref.index)}")
  assert dq < QPOS_TOL and dv < QVEL_TOL, (ref.suite, ref.index, dq, dv)
  assert np.array_equal(success, ref.success), (ref.suite, ref.index)


@pytest.fixture(scope="module", params=DEFAULT, ids=[f"{s}-{i}" for s, i in DEFAULT])
def reference(request):
  return record(*request.param)


def test_rollouts_follow_the_reference_env(reference):
  check_parity(reference)


def test_observations_and_cameras_are_the_reference_envs(reference):
  """LIBERO's observations (proprioception, objects, both cameras at 128x128) after the reset and
  after each of 3 steps, against the reference's with its cameras on: images pixel for pixel."""
  env = scene.reference_env(reference.suite, reference.index)
  b = engine.LiberoBatch(reference.scene, 1, nthread=1, render=True)
  try:
    got, want = [], [env.set_init_state(reference.states[0])]
    b.reset(reference.states)
    got.append(b.observe())
    for a in reference.actions[0, :3]:
      want.append(env.step(a)[0])
      b.step(a[None])
      got.append(b.observe())
  finally:
    env.close()
    b.close()
  for k, (ours, ref) in enumerate(zip(got, want)):
    for name, value in ours.items():
      theirs = np.asarray(ref[name])
      if name.endswith("_image"):
        diff = np.abs(value[0].astype(int) - theirs[::-1])  # robosuite's rows are bottom-up
        # Identical at the init state; after steps a state 1e-8 apart can move an edge's multisample
        # coverage by a level.
        assert (diff.max() == 0) if k == 0 else ((diff > 8).mean() < 2e-3 and diff.mean() < 0.05), (
            reference.suite, reference.index, k, name, diff.mean(), diff.max())
      elif name.endswith("quat"):
        assert min(np.abs(value[0] - theirs).max(), np.abs(value[0] + theirs).max()) < QPOS_TOL, (k, name)
      else:
        assert np.abs(value[0] - theirs).max() < QPOS_TOL, (k, name, value[0], theirs)
  assert {"agentview_image", "robot0_eye_in_hand_image", "robot0_eef_pos", "robot0_gripper_qpos"} <= set(got[0])


class _Departing(engine.LiberoBatch):
  """Our engine with one thing wrong, to show that the parity tolerance catches it."""
  wrong = "kp"

  def __init__(self, s, num_envs, nthread=0):
    super().__init__(s, num_envs, nthread)
    if self.wrong == "kp":
      self.params = dataclasses.replace(self.params, kp=tuple(1.01 * k for k in self.params.kp))
    elif self.wrong == "fresh first step":
      self._reset_arm = None

  def _controller_reading(self):
    return self.arm() if self._reset_arm is None else super()._controller_reading()


@pytest.mark.parametrize("wrong", ["kp", "fresh first step"])
def test_a_controller_that_departs_from_the_reference_is_caught(wrong):
  ref = record(*DEFAULT[1])
  cls = type("Wrong", (_Departing,), {"wrong": wrong})
  qpos, qvel, _, _ = rollout(ref.scene, ref.states, ref.actions, batch_cls=cls)
  dq, dv = errors(ref, qpos, qvel)
  assert dq > 10 * QPOS_TOL, (wrong, dq, dv)


def test_a_batch_steps_each_environment_as_alone():
  s = scene.scene(*DEFAULT[2])
  states = suites.init_states(*DEFAULT[2])[[3, 11, 29]]
  acts = np.stack([actions(8, k) for k in range(3)])
  together = rollout(s, states, acts)[0]
  for i in range(3):
    alone = rollout(s, states[i:i + 1], acts[i:i + 1])[0]
    # The same physics; numpy's batched linear algebra rounds differently with the batch's size.
    assert np.abs(alone[0] - together[i]).max() < 1e-12, i


def test_bad_actions_and_states_say_what_is_wrong():
  s = scene.scene(*DEFAULT[1])
  b = engine.LiberoBatch(s, 2, nthread=1)
  with pytest.raises(RuntimeError, match="step before reset"):
    b.step(np.zeros((2, 7)))
  with pytest.raises(ValueError, match="got 3 states for 2 environments"):
    b.reset(suites.init_states(*DEFAULT[1])[:3])
  b.reset(suites.init_states(*DEFAULT[1])[:2])
  with pytest.raises(ValueError, match=r"actions have shape \(2, 4\), expected \(2, 7\)"):
    b.step(np.zeros((2, 4)))
  with pytest.raises(ValueError, match="an init state of another task"):
    b.reset(suites.init_states(*DEFAULT[0])[:2])


def test_the_gripper_command_integrates_and_saturates():
  p = osc.params(scene.scene(*DEFAULT[1]).meta)
  state = osc.initial_state(p, 3)
  for _ in range(30):
    ctrl, state = osc.gripper(p, state, np.array([1.0, -1.0, 0.0]))
  assert np.allclose(state.gripper, [[-0.3, 0.3], [0.3, -0.3], [0.0, 0.0]])
  for _ in range(200):
    ctrl, state = osc.gripper(p, state, np.array([1.0, -1.0, 0.0]))
  assert np.allclose(state.gripper[:2], [[-1, 1], [1, -1]])
  assert np.allclose(ctrl[0], [p.gripper_ctrl_min[0], p.gripper_ctrl_max[1]])  # closed: both fingers in


@pytest.mark.sweep
@pytest.mark.parametrize("suite,index", SWEEP, ids=[f"{s}-{i}" for s, i in SWEEP])
def test_every_other_task_follows_the_reference(suite, index):
  check_parity(record(suite, index))

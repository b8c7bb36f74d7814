"""Skill labels mined from demonstrations (data/segments.py) and their path into training batches."""

import jax
import numpy as np
import pytest

from envs import toy_skills as toy
from experiments import toy_skills as toy_exp
from skillplug_jax.data import loader, segments
from skillplug_jax.train import loop
from skillplug_jax.train.config import TrainConfig, override

OPEN, CLOSED = 0.04, 0.0


def tabletop_episode():
  """Reach (10 steps), close (5), carry (10, the object moving 2 cm a step), open and back off (20)."""
  T = 45
  grip = np.full(T, OPEN)
  grip[10:25] = CLOSED
  obj = np.zeros((T, 14))
  obj[15:25, 0] = 0.02 * np.arange(1, 11)  # object 0's x while carried
  obj[25:, 0] = obj[24, 0]
  obj[:, 7:] = 0.3  # a second object that never moves
  joint_pos = np.zeros((T, 7))
  joint_pos[:, -1] = grip
  action = np.zeros((T, 7))
  action[:, -1] = grip
  return joint_pos, obj, action


def test_tabletop_phases_follow_the_gripper_and_what_moves():
  joint_pos, obj, action = tabletop_episode()
  labels = segments.tabletop_phases(joint_pos, obj, action, window=5, moved=0.01, after=15)
  want = []  # the definition, step by step
  for t in range(45):
    ahead = min(t + 5, 44)
    moving = np.abs(obj[ahead] - obj[t]).max() > 0.01
    if moving:
      want.append(2)
    elif action[t, -1] < 0.01:
      want.append(1)
    else:
      last = max([s for s in range(t + 1) if np.abs(obj[min(s + 5, 44)] - obj[s]).max() > 0.01], default=-99)
      want.append(3 if t - last <= 15 else 0)
  np.testing.assert_array_equal(labels, want)
  # and in words: reach, carry (from 5 steps before the object moves), release, reach again
  assert list(labels[:10]) == [0] * 10 and labels[20] == 2 and labels[24] == 1
  assert list(labels[25:39]) == [3] * 14 and list(labels[40:]) == [0] * 5
  assert set(labels) == {0, 1, 2, 3}


def test_a_pushed_object_is_transport_whatever_the_gripper():
  joint_pos, obj, action = tabletop_episode()
  action[:, -1] = OPEN  # pushed, not carried
  labels = segments.tabletop_phases(joint_pos, obj, action)
  assert labels[15] == 2 and 1 not in set(labels)


def test_labels_do_not_look_across_episodes():
  joint_pos, obj, action = tabletop_episode()
  still = np.zeros_like(obj)
  # episode 0 never moves; episode 1 starts with its object far away: a window crossing the
  # boundary would call the end of episode 0 transport
  moved = obj + 5.0
  steps = [np.concatenate(x) for x in ((joint_pos, joint_pos), (still, moved), (action, action))]
  labels = segments.label_steps("tabletop_phases", *steps, start=np.array([0, 45]), length=np.array([45, 45]))
  assert 2 not in set(labels[:45])
  np.testing.assert_array_equal(labels[45:], segments.tabletop_phases(joint_pos, moved, action))
  with pytest.raises(ValueError, match="unknown skill labeller 'phases'"):
    segments.label_steps("phases", *steps, start=np.array([0]), length=np.array([90]))


def test_toy_targets_recover_the_toy_primitive_exactly():
  data = toy_exp.demo_arrays(toy.ToySkillsConfig(), jax.random.PRNGKey(3), toy.SEEN, 4, chunk=8)
  agreement = toy_exp.mined_label_agreement(data)
  assert agreement == dict(labeller="toy_targets", nmi=pytest.approx(1.0), equal=1.0)
  assert set(np.unique(data["mined"][:, 0])) <= {0, 1, 2}  # every task starts with a reach


def demonstrations(episodes=3, length=12) -> loader.Demonstrations:
  rng = np.random.default_rng(0)
  n = episodes * length
  steps = dict(joint_pos=rng.normal(size=(n, 7)).astype(np.float32),
               object_state=rng.normal(size=(n, 14)).astype(np.float32),
               action=rng.normal(size=(n, 7)).astype(np.float32))
  stats = {k: dict(mean=np.zeros(v.shape[1]), std=np.ones(v.shape[1])) for k, v in steps.items()}
  return loader.Demonstrations(path=None, tasks=("jujube_pick",), image_size=None, steps=steps,
                               start=np.arange(episodes) * length, length=np.full(episodes, length),
                               task_id=np.zeros(episodes, np.int32),
                               episode_id=tuple(f"jujube_pick/{e}" for e in range(episodes)), stats=stats)


def test_batches_carry_the_labels_of_their_rows():
  d = demonstrations()
  labels = np.arange(len(d.steps["action"])) % 4
  ld = loader.ChunkLoader(d, batch_size=6, chunk=4, seed=0, skill_labels=labels)
  ep, t = ld.indices(0)
  np.testing.assert_array_equal(ld.numpy_batch(0)["skill_label"], labels[d.start[ep] + t])
  assert "skill_label" not in loader.ChunkLoader(d, batch_size=6, chunk=4).numpy_batch(0)
  with pytest.raises(ValueError, match="3 skill labels for"):
    loader.ChunkLoader(d, batch_size=6, chunk=4, skill_labels=labels[:3])
  cfg = toy_exp.toy_train_config()
  assert loop.skill_labels(cfg, d) is None
  mined = loop.skill_labels(override(cfg, ["skill_labels=tabletop_phases"]), d)
  assert mined.shape == labels.shape and set(mined) <= {0, 1, 2, 3}


@pytest.mark.slow
def test_the_toy_refuses_a_tabletop_labeller():
  exp = toy_exp.ToyExperiment(demos_seen=2)
  cfg = override(exp.train, ["skill_labels=tabletop_phases", "loss.router_label=1", "max_steps=1"])
  data = toy_exp.demo_arrays(exp.env, jax.random.PRNGKey(0), (0,), 2, chunk=8)
  params = toy_exp.init_params(cfg.model, jax.random.PRNGKey(0))
  with pytest.raises(ValueError, match="the toy's labeller is 'toy_targets'"):
    toy_exp.train(cfg, params, data, jax.random.PRNGKey(0), steps_per_call=1, progress=False)

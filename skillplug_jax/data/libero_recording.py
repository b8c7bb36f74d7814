"""Record the scripted LIBERO experts (`envs.libero.expert`) as demonstrations, batched.

A batch of one task starts from drawn initial states (`envs.libero.starts`: LIBERO's samplers,
not the benchmark's init states that evaluation uses), settles as LIBERO's evaluations do (10
no-op steps, not recorded), then the expert acts. Step t of an episode holds what a policy would
have seen (our LIBERO layout, `envs.libero.layout`, and both cameras) and the action the expert
then sent. An episode ends at the step its success is declared: the goal achieved within the
suite's time limit and held, the gripper open and the hand withdrawn, for
`expert.HOLD_STEPS` steps (the rule of `expert.run`); the others are failures.
"""

from __future__ import annotations

import numpy as np

from envs.libero import engine, expert, layout, starts, suites
from envs.libero import scene as scenes
from envs.libero.rollout import REST
from skillplug_jax.data.recording import Episode


def record_expert(name: str, first: int, num: int, seed: int = 0, images: bool = True, image_size: int = 64,
                  multisample: bool = False, nthread: int = 0) -> list[Episode]:
  """The expert's episodes from drawn starts `first` .. `first + num - 1` of `seed` of LIBERO task
  `name` ("<suite>:<index>"). Cameras are drawn at `image_size` (square) as LIBERO's renderer draws
  them, without its 4x multisampling unless `multisample` (2.3x faster on a CPU's software GL)."""
  task = suites.parse(name)
  s = scenes.scene(task.suite, task.index)
  layout.check_fits(s.meta)
  states = starts.starts(task.suite, task.index, first + num, seed)[first:]
  batch = engine.LiberoBatch(s, num, nthread=nthread, render=images, image_size=image_size, multisample=multisample)
  try:
    batch.reset(states)
    rest = np.tile(REST, (num, 1))
    for _ in range(suites.SETTLE_STEPS):
      batch.step(rest)
    scripted = expert.Expert(batch)
    limit = task.time_limit
    frames, actions = [], []
    reached = np.full(num, -1)  # the first step at which the goal holds, within the limit
    held = np.zeros(num, np.int64)
    declared = np.full(num, -1)  # the step at which success is declared
    for k in range(limit + expert.HOLD_STEPS):
      obs = batch.observe()
      step = layout.observation(s.meta, obs, batch.observed_qpos())
      if images:
        for ours, theirs in zip(layout.CAMERAS, scenes.CAMERAS):
          step[f"{ours}_rgb"] = obs[f"{theirs}_image"]
      act = scripted.act() if k < limit else rest
      frames.append(step)
      actions.append(np.asarray(act, np.float32))
      batch.step(act)
      ok = batch.success()
      reached[(reached < 0) & ok & (k < limit)] = k
      held = np.where(ok & (scripted.phase == expert.DONE), held + 1, 0)
      declared[(declared < 0) & (held >= expert.HOLD_STEPS) & (reached >= 0)] = k
      if (declared >= 0).all():
        break
  finally:
    batch.close()
  episodes = []
  for b in range(num):
    length = declared[b] + 1 if declared[b] >= 0 else len(actions)
    observation = {key: np.stack([f[key][b] for f in frames[:length]]) for key in frames[0]}
    nan = not all(np.isfinite(observation[key]).all() for key, _ in layout.STATE)
    episodes.append(Episode(observation=observation, action=np.stack([a[b] for a in actions[:length]]),
                            success=bool(declared[b] >= 0 and not nan), nan=nan))
  return episodes

"""Record scripted-expert episodes: observations and actions of every control step.

The experts run through the episode engine (`envs.rollout.run_episodes`,
`record=True`), as policies do in evaluation. An episode's steps are those
taken before it ended (success declared, NaN or time limit): step t holds
the observation the expert saw and the action it sent.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

import envs
from envs import rollout


class Episode(NamedTuple):
  """One recorded episode, host-side numpy."""
  observation: dict  # joint_pos [T,7], object_state [T,OBJECT_STATE_DIM], *_rgb [T,H,W,3] uint8
  action: np.ndarray  # [T, 7]
  success: bool
  nan: bool
  overflow: int = 0  # the physics' overflow bits (envs.env.solver_limit_counts)


def record_expert(benv, keys: jax.Array) -> list[Episode]:
  """Run the task's expert on a batch of seeded resets; return every episode."""
  out = rollout.run_episodes(benv, rollout.expert_controller(benv), keys, record=True)
  traj = out.trajectory
  obs = dict(traj.observation)
  obs["object_state"] = np.asarray(envs.padded_object_state(obs["object_state"]))
  episodes = []
  for b in range(benv.num_envs):
    length = int(traj.alive[:, b].sum())  # alive is a prefix: done never clears
    episodes.append(Episode(
        observation={k: v[:length, b] for k, v in obs.items()},
        action=traj.action[:length, b].astype(np.float32),
        success=bool(out.success[b]), nan=bool(out.nan[b]), overflow=int(out.overflow[b])))
  return episodes

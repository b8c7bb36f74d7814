"""Record scripted-expert episodes: observations and actions of every control step.

The batch advances in jitted `lax.scan` blocks of `BLOCK` control steps; after
each block the steps come back to the host, and the loop stops once every
episode has ended, so a batch of short episodes never simulates the longest
time limit. An episode's steps are those taken before it ended (success, NaN
or time limit): step t holds the observation the expert saw and the action it
sent.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs import expert
from envs.batched import BatchedEnv

BLOCK = 20  # control steps per jitted block (1 s simulated): little overshoot past the last episode


class Episode(NamedTuple):
  """One recorded episode, host-side numpy."""
  observation: dict  # joint_pos [T,7], object_state [T,OBJECT_STATE_DIM], *_rgb [T,H,W,3] uint8
  action: np.ndarray  # [T, 7]
  success: bool
  nan: bool
  overflow: int = 0  # the physics' overflow bits (envs.env.solver_limit_counts)


@functools.lru_cache(maxsize=None)
def _block_fn(benv: BatchedEnv):
  env = benv.env

  def observe(state):
    obs = dict(state.obs)
    obs["object_state"] = envs.padded_object_state(obs["object_state"])
    return obs

  def one_step(carry, _):
    state, xs = carry
    alive = state.done == 0
    action, xs = jax.vmap(lambda d, x: expert.act(env, d, x))(state.pipeline_state, xs)
    record = (observe(state), action, alive)
    return (benv.step(state, action), xs), record

  def block(state, xs):
    return jax.lax.scan(one_step, (state, xs), None, length=BLOCK)

  def start(keys):
    state = benv.reset(keys)
    return state, jax.vmap(lambda s: expert.init(env, s))(state)

  return jax.jit(start), jax.jit(block)


def record_expert(benv: BatchedEnv, keys: jax.Array) -> list[Episode]:
  """Run the task's expert on a batch of seeded resets; return every episode."""
  start, block = _block_fn(benv)
  state, xs = start(keys)
  limit = benv.episode_length
  chunks, t = [], 0
  while t < limit:
    (state, xs), rec = block(state, xs)
    chunks.append(jax.device_get(rec))
    t += BLOCK
    if bool(jnp.all(state.done > 0)):
      break
  obs = {k: np.concatenate([c[0][k] for c in chunks], axis=0)[:limit] for k in chunks[0][0]}
  action = np.concatenate([c[1] for c in chunks], axis=0)[:limit]
  alive = np.concatenate([c[2] for c in chunks], axis=0)[:limit]
  first = np.asarray(state.info["first_success_step"])
  nan = np.asarray(state.metrics["nan"]) > 0
  overflow = np.asarray(state.metrics["overflow"])
  episodes = []
  for b in range(benv.num_envs):
    length = int(alive[:, b].sum())  # alive is a prefix: done never clears
    episodes.append(Episode(
        observation={k: v[:length, b] for k, v in obs.items()},
        action=action[:length, b].astype(np.float32),
        success=bool(first[b] >= 0), nan=bool(nan[b]), overflow=int(overflow[b])))
  return episodes

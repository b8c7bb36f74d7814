"""Expert rollouts: the whole batch, every control step, in one jitted loop.

`lax.while_loop` stops as soon as every episode has ended (success declared,
NaN) or the task's time limit is reached, so short tasks do not pay for long
ones.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from envs import expert
from envs.batched import BatchedEnv


class ExpertResult(NamedTuple):
  success: np.ndarray  # [B] bool: success within the time limit
  first_success_step: np.ndarray  # [B] control steps to success (-1 if never)
  nan: np.ndarray  # [B] bool: physics blew up
  steps_run: int  # control steps simulated for the batch
  overflow: np.ndarray  # [B] int: the physics' overflow bits (envs.env.solver_limit_counts)


def reset_keys(seed: int, num: int, offset: int = 0) -> jax.Array:
  """Per-episode reset keys: episode i of a seed always gets the same key."""
  base = jax.random.PRNGKey(seed)
  return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(offset, offset + num))


@functools.lru_cache(maxsize=None)
def _expert_loop(benv: BatchedEnv):
  env = benv.env
  limit = env.episode_length

  def run(keys):
    state = benv.reset(keys)
    xs = jax.vmap(lambda s: expert.init(env, s))(state)

    def cond(carry):
      t, state, _ = carry
      return (t < limit) & ~jnp.all(state.done > 0)

    def body(carry):
      t, state, xs = carry
      action, xs = jax.vmap(lambda d, x: expert.act(env, d, x))(state.pipeline_state, xs)
      return t + 1, benv.step(state, action), xs

    t, state, _ = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), state, xs))
    return t, state.info["first_success_step"], state.metrics["nan"], state.metrics["overflow"]

  return jax.jit(run)


def run_expert(benv: BatchedEnv, keys: jax.Array) -> ExpertResult:
  t, first, nan, overflow = jax.device_get(_expert_loop(benv)(keys))
  first = np.asarray(first)
  return ExpertResult(success=first >= 0, first_success_step=first,
                      nan=np.asarray(nan) > 0, steps_run=int(t), overflow=np.asarray(overflow))

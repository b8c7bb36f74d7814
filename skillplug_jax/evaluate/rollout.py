"""Closed-loop evaluation: a batch of environments and a controller in one jitted loop.

A `Controller` is a pair of pure functions over the batch and the arrays
they read (`weights`: a policy's parameters and statistics):
  init(state) -> cstate
  act(weights, cstate, state, t) -> (actions [B, 7], cstate, info)
where info may hold `routing` [B, K] (the router's weights) and `queried`
[B] bool (whether the policy was asked this step; default: every step), and `state` is the batched Brax state (a learned policy reads `state.obs`;
the scripted expert also reads the privileged `state.pipeline_state`). The
whole episode batch runs inside one `lax.while_loop` (render -> controller ->
physics substeps per control step) that stops when every episode has ended or
the task's time limit is reached; nothing returns to Python until then. An
episode stops counting at its first success; a NaN state fails that episode
only (the environment keeps its last finite state and marks it).
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from envs import expert
from envs.batched import BatchedEnv


class Controller(NamedTuple):
  init: Callable
  act: Callable
  num_skills: int = 0  # > 0: act returns routing weights to record
  name: str = ""
  # Passed into the jitted loop as an argument, not baked in as constants:
  # runs of the same model (training seeds) share one compiled loop.
  weights: Any = ()


class EpisodeResults(NamedTuple):
  success: np.ndarray  # [B] bool
  first_success_step: np.ndarray  # [B] control steps to success, -1 if none
  nan: np.ndarray  # [B] bool: the physics blew up (counted as a failure)
  queries: np.ndarray  # [B] policy queries made before the episode ended
  routing: np.ndarray | None  # [T, B, K] routing weights at each query (NaN where none)
  steps_run: int


def expert_controller(benv: BatchedEnv) -> Controller:
  """The task's scripted expert as a controller (the engine's end-to-end check)."""
  env = benv.env

  def init(state):
    return jax.vmap(lambda s: expert.init(env, s))(state)

  def act(weights, cstate, state, t):
    action, cstate = jax.vmap(lambda d, x: expert.act(env, d, x))(state.pipeline_state, cstate)
    return action, cstate, {}

  return Controller(init, act, 0, "expert")


@functools.lru_cache(maxsize=None)
def _episode_loop(benv: BatchedEnv, init: Callable, act: Callable, k: int):
  limit = benv.episode_length

  def run(weights, keys):
    state = benv.reset(keys)
    b = keys.shape[0]
    carry = dict(t=jnp.zeros((), jnp.int32), state=state, cstate=init(state),
                 queries=jnp.zeros((b,), jnp.int32),
                 routing=jnp.full((limit, b, max(k, 1)), jnp.nan, jnp.float32))

    def cond(c):
      return (c["t"] < limit) & ~jnp.all(c["state"].done > 0)

    def body(c):
      alive = c["state"].done == 0
      actions, cstate, info = act(weights, c["cstate"], c["state"], c["t"])
      queried = info.get("queried", jnp.ones_like(alive)) & alive
      routing = info.get("routing")
      new = dict(t=c["t"] + 1, state=benv.step(c["state"], actions), cstate=cstate,
                 queries=c["queries"] + queried.astype(jnp.int32), routing=c["routing"])
      if routing is not None:
        row = jnp.where(queried[:, None], routing.astype(jnp.float32), jnp.nan)
        new["routing"] = jax.lax.dynamic_update_index_in_dim(c["routing"], row, c["t"], 0)
      return new

    c = jax.lax.while_loop(cond, body, carry)
    return dict(t=c["t"], first=c["state"].info["first_success_step"], nan=c["state"].metrics["nan"],
                queries=c["queries"], routing=c["routing"])

  return jax.jit(run)


def evaluate(benv: BatchedEnv, controller: Controller, keys: jax.Array) -> EpisodeResults:
  """Run one batch of episodes from reset keys `keys` [B, 2] to the end."""
  loop = _episode_loop(benv, controller.init, controller.act, controller.num_skills)
  out = jax.device_get(loop(controller.weights, keys))
  first = np.asarray(out["first"])
  steps = int(out["t"])
  routing = np.asarray(out["routing"])[:steps] if controller.num_skills else None
  return EpisodeResults(success=first >= 0, first_success_step=first, nan=np.asarray(out["nan"]) > 0,
                        queries=np.asarray(out["queries"]), routing=routing, steps_run=steps)

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
episode ends when its success is declared (the task's predicate held for
`SUCCESS_HOLD_STEPS`); a NaN state fails that episode only (the environment
keeps its last finite state and marks it).

With several local devices the episode batch is split over them with
`shard_map`: each device runs the same loop on its share of environments
(`benv` is sized for one share) and stops when its own episodes have ended.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P

from envs import expert
from envs.batched import BatchedEnv
from envs.env import SUCCESS_HOLD_STEPS


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
  frames: list | None = None  # side camera [T_i + 1, H, W, 3] uint8 of the first episodes: start to end
  overflow: np.ndarray | None = None  # [B] int: the physics' overflow bits (envs.env.solver_limit_counts)


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
def _episode_loop(benv: BatchedEnv, init: Callable, act: Callable, k: int, devices: tuple | None,
                  frames: int):
  limit = benv.episode_length

  def run(weights, keys):
    state = benv.reset(keys)
    b = keys.shape[0]
    carry = dict(t=jnp.zeros((), jnp.int32), state=state, cstate=init(state),
                 queries=jnp.zeros((b,), jnp.int32),
                 routing=jnp.full((limit, b, max(k, 1)), jnp.nan, jnp.float32))
    if frames:  # frame 0 is the start, frame t the side camera after t control steps
      carry["frames"] = jnp.zeros((limit + 1, frames) + state.obs["side_rgb"].shape[1:], jnp.uint8)
      carry["frames"] = carry["frames"].at[0].set(state.obs["side_rgb"][:frames])

    def cond(c):
      return (c["t"] < limit) & ~jnp.all(c["state"].done > 0)

    def body(c):
      alive = c["state"].done == 0
      actions, cstate, info = act(weights, c["cstate"], c["state"], c["t"])
      queried = info.get("queried", jnp.ones_like(alive)) & alive
      routing = info.get("routing")
      state = benv.step(c["state"], actions)
      new = dict(t=c["t"] + 1, state=state, cstate=cstate,
                 queries=c["queries"] + queried.astype(jnp.int32), routing=c["routing"])
      if routing is not None:
        row = jnp.where(queried[:, None], routing.astype(jnp.float32), jnp.nan)
        new["routing"] = jax.lax.dynamic_update_index_in_dim(c["routing"], row, c["t"], 0)
      if frames:
        new["frames"] = jax.lax.dynamic_update_index_in_dim(
            c["frames"], state.obs["side_rgb"][:frames], c["t"] + 1, 0)
      return new

    c = jax.lax.while_loop(cond, body, carry)
    return dict(t=jnp.full((b,), c["t"]), first=c["state"].info["first_success_step"], nan=c["state"].metrics["nan"],
                overflow=c["state"].metrics["overflow"], queries=c["queries"], routing=c["routing"],
                frames=c.get("frames", jnp.zeros((1, 0))))

  if devices is None:
    return jax.jit(run)
  mesh = Mesh(np.asarray(devices), ("batch",))
  per_env = P("batch")
  out_specs = dict(t=per_env, first=per_env, nan=per_env, overflow=per_env, queries=per_env, routing=P(None, "batch"),
                   frames=P(None, "batch"))
  # The physics is an opaque Warp call with no replication rules: skip the check.
  return jax.jit(jax.shard_map(run, mesh=mesh, in_specs=(P(), per_env), out_specs=out_specs,
                               check_vma=False))


def local_devices_for(batch: int, render: bool = False) -> tuple | None:
  """The local devices an evaluation batch is split over (None: just one).

  A rendering batch is split over GPUs only: Warp has one CPU device, so CPU
  shards would share (and race on) one render context.
  """
  devices = jax.local_devices()
  if len(devices) < 2 or batch < len(devices) or (render and devices[0].platform != "gpu"):
    return None
  return tuple(devices)


def evaluate(benv: BatchedEnv, controller: Controller, keys: jax.Array,
             devices: tuple | None = None, frames: int = 0) -> EpisodeResults:
  """Run one batch of episodes from reset keys `keys` [B, 2] to the end.

  devices: split the batch over these devices, `benv.num_envs` environments
  on each (B = len(devices) * benv.num_envs); None runs it all on one.
  frames: also return the side camera of the first `frames` episodes
  (needs a rendering `benv`, at most `benv.num_envs`).
  """
  n = 1 if devices is None else len(devices)
  if keys.shape[0] != n * benv.num_envs:
    raise ValueError(f"{keys.shape[0]} reset keys for {n} device(s) x {benv.num_envs} environments")
  if frames and (not benv.render or frames > benv.num_envs):
    raise ValueError(f"frames={frames} needs a rendering environment batch of at least that many")
  if benv.render and n > 1 and tuple(benv.devices or ()) != tuple(devices):
    raise ValueError("a rendering batch split over devices needs an environment made for them "
                     "(envs.make(..., devices=...): one render context per device)")
  loop = _episode_loop(benv, controller.init, controller.act, controller.num_skills,
                       None if devices is None else tuple(devices), frames)
  out = jax.device_get(loop(controller.weights, keys))
  first = np.asarray(out["first"])
  ran = np.asarray(out["t"])  # control steps each environment's loop ran (its device's)
  steps = int(ran.max())
  routing = np.asarray(out["routing"])[:steps] if controller.num_skills else None
  video = None
  if frames:  # episode i from its start to the step its success was declared, or to the last step run
    ends = np.where(first >= 0, first + SUCCESS_HOLD_STEPS - 1, ran)
    video = [np.asarray(out["frames"])[:ends[i] + 1, i] for i in range(frames)]
  return EpisodeResults(success=first >= 0, first_success_step=first, nan=np.asarray(out["nan"]) > 0,
                        queries=np.asarray(out["queries"]), routing=routing, steps_run=steps, frames=video,
                        overflow=np.asarray(out["overflow"]))

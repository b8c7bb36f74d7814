"""The episode engine: a batch of environments driven to the end by a controller.

Scripted experts (evaluation of the benchmark, demonstrations) and learned
policies (closed-loop evaluation) all run here. A `Controller` is a pair of
pure functions over the batch and the arrays they read (`weights`: a
policy's parameters and statistics):
  init(state) -> cstate
  act(weights, cstate, state, t) -> (actions [B, 7], cstate, info)
where info may hold `routing` [B, K] (the router's weights) and `queried`
[B] bool (whether the policy was asked this step; default: every step), and
`state` is the batched Brax state (a learned policy reads `state.obs`; the
scripted expert also reads the privileged `state.pipeline_state`).

The loop stops when every episode has ended (success declared, NaN) or the
task's time limit is reached. On `mjx-warp` the whole loop (controller ->
physics substeps -> rendering, per control step) is one jitted
`lax.while_loop`, and nothing returns to Python until the end; with several
local devices the batch is split over them with `shard_map`. On `mujoco` the
physics runs in C, so each control step is one jitted controller call and
one batch step of the C engine (`envs.mujoco_batch`).

`record=True` also returns every step's observation, action and whether the
episode was still running (demonstrations): on `mjx-warp` into buffers of the
time limit's length, so a rendering batch needs memory for its full images.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P

from envs import expert
from envs.env import SUCCESS_HOLD_STEPS


class Controller(NamedTuple):
  init: Callable
  act: Callable
  num_skills: int = 0  # > 0: act returns routing weights to record
  name: str = ""
  # Passed into the jitted loop as an argument, not baked in as constants:
  # runs of the same model (training seeds) share one compiled loop.
  weights: Any = ()
  # (H, W) of the camera images the controller reads; None: it reads no camera (a state policy,
  # the scripted expert). Evaluation renders at this size whatever its caller asked.
  image_size: tuple[int, int] | None = None
  # A policy that reads its task's instruction: text -> the word ids it reads (`state.obs["instruction"]`,
  # filled by the episode engine of a benchmark with instructions: envs/libero/rollout.py). None: none.
  instruction: Callable | None = None


class Trajectory(NamedTuple):
  """Every control step of a batch: step t holds what the controller saw and sent."""
  observation: dict  # joint_pos [T, B, 7], object_state [T, B, D] (the task's width), *_rgb
  action: np.ndarray  # [T, B, 7]
  alive: np.ndarray  # [T, B] bool: the episode had not ended (a prefix of each column)


class EpisodeResults(NamedTuple):
  success: np.ndarray  # [B] bool
  first_success_step: np.ndarray  # [B] control steps to success, -1 if none
  nan: np.ndarray  # [B] bool: the physics blew up (counted as a failure)
  queries: np.ndarray  # [B] policy queries made before the episode ended
  routing: np.ndarray | None  # [T, B, K] routing weights at each query (NaN where none)
  steps_run: int
  frames: list | None = None  # side camera [T_i + 1, H, W, 3] uint8 of the first episodes: start to end
  overflow: np.ndarray | None = None  # [B] int: the physics' overflow bits (envs.env.solver_limit_counts)
  trajectory: Trajectory | None = None  # with record=True


def reset_keys(seed: int, num: int, offset: int = 0) -> jax.Array:
  """Per-episode reset keys: episode i of a seed always gets the same key."""
  base = jax.random.PRNGKey(seed)
  return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(offset, offset + num))


@functools.lru_cache(maxsize=None)
def expert_controller(benv) -> Controller:
  """The task's scripted expert as a controller (one per batch: its compiled loop is reused)."""
  env = benv.env

  def init(state):
    return jax.vmap(lambda s: expert.init(env, s))(state)

  def act(weights, cstate, state, t):
    action, cstate = jax.vmap(lambda d, x: expert.act(env, d, x))(state.pipeline_state, cstate)
    return action, cstate, {}

  return Controller(init, act, 0, "expert")


def local_devices_for(batch: int, render: bool = False, backend: str = "mjx-warp") -> tuple | None:
  """The local devices an evaluation batch is split over (None: just one).

  The C engine runs on the CPU's threads, not on JAX devices. A rendering
  batch is split over GPUs only: Warp has one CPU device, so CPU shards would
  share (and race on) one render context.
  """
  devices = jax.local_devices()
  if (backend != "mjx-warp" or len(devices) < 2 or batch < len(devices)
      or (render and devices[0].platform != "gpu")):
    return None
  return tuple(devices)


def run_episodes(benv, controller: Controller, keys: jax.Array, devices: tuple | None = None,
                 frames: int = 0, record: bool = False) -> EpisodeResults:
  """Run one batch of episodes from reset keys `keys` [B, 2] to the end.

  devices: split the batch over these devices, `benv.num_envs` environments
  on each (B = len(devices) * benv.num_envs); None runs it all on one.
  frames: also return the side camera of the first `frames` episodes
  (needs a rendering `benv`, at most `benv.num_envs`).
  record: also return every step's observation and action (`Trajectory`).
  """
  n = 1 if devices is None else len(devices)
  if keys.shape[0] != n * benv.num_envs:
    raise ValueError(f"{keys.shape[0]} reset keys for {n} device(s) x {benv.num_envs} environments")
  if frames and (not benv.render or frames > benv.num_envs):
    raise ValueError(f"frames={frames} needs a rendering environment batch of at least that many")
  if n > 1 and benv.backend != "mjx-warp":
    raise ValueError(f"the {benv.backend!r} backend runs on the CPU's threads: it takes no devices")
  if benv.render and n > 1 and tuple(benv.devices or ()) != tuple(devices):
    raise ValueError("a rendering batch split over devices needs an environment made for them "
                     "(envs.make(..., devices=...): one render context per device)")
  if benv.backend == "mujoco":
    out = _host_loop(benv, controller, keys, frames, record)
  else:
    loop = _device_loop(benv, controller.init, controller.act, controller.num_skills,
                        None if devices is None else tuple(devices), frames, record)
    out = jax.device_get(loop(controller.weights, keys))
  first = np.asarray(out["first"])
  ran = np.asarray(out["t"])  # control steps each environment's loop ran (its device's)
  steps = int(ran.max())
  routing = np.asarray(out["routing"])[:steps] if controller.num_skills else None
  video = None
  if frames:  # episode i from its start to the step its success was declared, or to the last step run
    ends = np.where(first >= 0, first + SUCCESS_HOLD_STEPS - 1, ran)
    video = [np.asarray(out["frames"])[:ends[i] + 1, i] for i in range(frames)]
  trajectory = None
  if record:
    obs, action, alive = out["record"]
    trajectory = Trajectory({k: np.asarray(v)[:steps] for k, v in obs.items()},
                            np.asarray(action)[:steps], np.asarray(alive)[:steps])
  return EpisodeResults(success=first >= 0, first_success_step=first, nan=np.asarray(out["nan"]) > 0,
                        queries=np.asarray(out["queries"]), routing=routing, steps_run=steps, frames=video,
                        overflow=np.asarray(out["overflow"]), trajectory=trajectory)


def _observed(state) -> dict:
  return {k: v for k, v in state.obs.items() if k in ("joint_pos", "object_state") or k.endswith("_rgb")}


@functools.lru_cache(maxsize=None)
def _device_loop(benv, init: Callable, act: Callable, k: int, devices: tuple | None, frames: int, record: bool):
  """The whole batch to the end in one jitted while_loop (MJX-Warp)."""
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
    if record:
      carry["record"] = (jax.tree.map(lambda x: jnp.zeros((limit,) + x.shape, x.dtype), _observed(state)),
                         jnp.zeros((limit, b, benv.env.action_size), jnp.float32),
                         jnp.zeros((limit, b), bool))

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
      if record:
        now = (_observed(c["state"]), actions.astype(jnp.float32), alive)
        new["record"] = jax.tree.map(lambda buf, x: jax.lax.dynamic_update_index_in_dim(buf, x, c["t"], 0),
                                     c["record"], now)
      return new

    c = jax.lax.while_loop(cond, body, carry)
    return dict(t=jnp.full((b,), c["t"]), first=c["state"].info["first_success_step"], nan=c["state"].metrics["nan"],
                overflow=c["state"].metrics["overflow"], queries=c["queries"], routing=c["routing"],
                frames=c.get("frames", jnp.zeros((1, 0))), record=c.get("record", ()))

  if devices is None:
    return jax.jit(run)
  mesh = Mesh(np.asarray(devices), ("batch",))
  per_env, per_step = P("batch"), P(None, "batch")
  out_specs = dict(t=per_env, first=per_env, nan=per_env, overflow=per_env, queries=per_env, routing=per_step,
                   frames=per_step, record=(per_step, per_step, per_step) if record else ())
  # The physics is an opaque Warp call with no replication rules: skip the check.
  return jax.jit(jax.shard_map(run, mesh=mesh, in_specs=(P(), per_env), out_specs=out_specs,
                               check_vma=False))


@functools.lru_cache(maxsize=None)
def _jitted(fn: Callable) -> Callable:
  return jax.jit(fn)


def _host_loop(benv, controller: Controller, keys, frames: int, record: bool) -> dict:
  """The C engine's loop: per control step, one jitted controller call and one batch step."""
  limit, b, k = benv.episode_length, keys.shape[0], controller.num_skills
  act, w = _jitted(controller.act), controller.weights
  state = benv.reset(keys)
  cstate = _jitted(controller.init)(state)
  queries = np.zeros(b, np.int32)
  routing = np.full((limit, b, max(k, 1)), np.nan, np.float32)
  video = [np.asarray(state.obs["side_rgb"][:frames])] if frames else []
  steps, t = [], 0
  done = np.asarray(state.done) > 0
  while t < limit and not done.all():
    actions, cstate, info = act(w, cstate, state, t)
    alive = ~done
    queried = np.asarray(info.get("queried", np.ones(b, bool))) & alive
    queries += queried
    if "routing" in info:
      routing[t] = np.where(queried[:, None], np.asarray(info["routing"], np.float32), np.nan)
    if record:
      steps.append((jax.device_get(_observed(state)), np.asarray(actions, np.float32), alive))
    state = benv.step(state, actions)
    done = np.asarray(state.done) > 0
    t += 1
    if frames:
      video.append(np.asarray(state.obs["side_rgb"][:frames]))
  out = dict(t=np.full(b, t), first=np.asarray(state.info["first_success_step"]),
             nan=np.asarray(state.metrics["nan"]), overflow=np.asarray(state.metrics["overflow"]),
             queries=queries, routing=routing, frames=np.stack(video) if frames else None)
  if record:
    obs = {key: np.stack([s[0][key] for s in steps]) for key in steps[0][0]} if steps else {}
    out["record"] = (obs, np.stack([s[1] for s in steps]) if steps else np.zeros((0, b, 7), np.float32),
                     np.stack([s[2] for s in steps]) if steps else np.zeros((0, b), bool))
  return out

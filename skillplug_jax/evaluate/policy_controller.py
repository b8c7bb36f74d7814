"""A trained policy as an evaluation controller: normalisation, chunking, temporal ensembling.

Temporal ensembling (ACT): the policy is queried every step; the action at t
averages every earlier chunk's prediction for t, weighted exp(-k i) with i = 0
for the oldest prediction. A ring buffer holds the last `chunk` chunks
([B, chunk, chunk, A]: row j is the chunk predicted j steps ago), so the
cost is constant in the episode length. Without ensembling the policy is
queried every `query_every` steps and its chunk runs open loop in between.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

import envs
from envs.rollout import Controller
from skillplug_jax.data import language
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.policy import Policy


def temporal_ensemble(buf, pred, t, k: float = 0.01):
  """Push chunk `pred` [B, C, A] (made at step t) and return (action at t, new buffer).

  buf [B, C, C, A]: row j is the chunk predicted j steps ago. The action
  averages row j's entry j over the rows that exist (j <= t), weighted
  exp(-k i) with i = 0 for the oldest, as ACT does.
  """
  chunk = pred.shape[1]
  buf = jnp.concatenate([pred[:, None], buf[:, :-1]], axis=1)
  ages = jnp.arange(chunk)
  candidates = buf[:, ages, ages]  # [B, C, A]: the chunk from j steps ago, its entry for now
  n = jnp.minimum(t + 1, chunk)
  w = jnp.where(ages < n, jnp.exp(-k * (n - 1 - ages)), 0.0)  # oldest (age n-1): exp(0)
  return jnp.einsum("j,bja->ba", w, candidates) / w.sum(), buf


def policy_controller(model: ModelConfig, params, stats: dict, *, query_every: int = 1,
                      ensemble: bool | None = None, ensemble_k: float = 0.01,
                      routing=None, routing_smoothing: float = 0.0, name: str = "") -> Controller:
  """routing: fixed weights ([K]) replace the router's (fixed- and mixed-skill rollouts).

  routing_smoothing s in [0, 1) (ours, a closed-loop probe of routing that chatters): each query
  decodes with r_t = s r_{t-1} + (1 - s) router(o_t) instead of the router's own weights (r_0 the
  router's); needs the router (no fixed routing) and a query every step."""
  if query_every < 1 or query_every > model.chunk:
    raise ValueError(f"query_every must be in 1..{model.chunk} (the chunk size), got {query_every}")
  temporal = (query_every == 1) if ensemble is None else ensemble
  if temporal and query_every != 1:
    raise ValueError("temporal ensembling queries the policy every step (query_every=1)")
  fixed = None if routing is None else tuple(float(r) for r in routing)
  if not 0.0 <= routing_smoothing < 1.0:
    raise ValueError(f"routing_smoothing must be in [0, 1), got {routing_smoothing}")
  if routing_smoothing and (fixed is not None or not model.is_skillplug or not temporal):
    raise ValueError("routing_smoothing needs an ACT+SkillPlug policy, its own router (no fixed routing) "
                     "and a query every step with temporal ensembling")
  init, act = _controller_fns(model, query_every, temporal, ensemble_k, fixed, float(routing_smoothing))
  inputs = ("action",) + tuple(model.proprio) + (("object_state",) if model.normalize_object_state else ())
  missing = [k for k in inputs if k not in stats]
  if missing:
    raise ValueError(f"the normalisation statistics have no {', '.join(missing)} entry "
                     "(this model reads it normalised)")
  weights = {"params": params,
             "stats": {k: {s: jnp.asarray(stats[k][s], jnp.float32) for s in ("mean", "std")}
                       for k in inputs}}
  instruction = None
  if model.instruction_vocab:
    if language.VOCABULARY_KEY not in stats:
      raise ValueError("this model reads instructions, but the run's statistics hold no vocabulary")
    vocab, width = tuple(stats[language.VOCABULARY_KEY]), model.instruction_words
    instruction = functools.partial(_instruction_ids, vocab=vocab, width=width)
  return Controller(init, act, model.plug.num_skills if model.is_skillplug else 0, name, weights,
                    tuple(model.image_size) if model.use_images else None, instruction)


def _instruction_ids(text: str, vocab: tuple, width: int):
  return language.encode([text], vocab, width)[0]


@functools.lru_cache(maxsize=None)
def _controller_fns(model: ModelConfig, query_every: int, temporal: bool, ensemble_k: float, fixed,
                    smoothing: float = 0.0):
  """(init, act) for one model and query scheme; cached so that runs of the
  same model reuse one compiled evaluation loop (their weights are arguments)."""
  policy = Policy(model)
  chunk, adim = model.chunk, model.action_dim
  routing = None if fixed is None else jnp.asarray(fixed, jnp.float32)

  def predict(weights, state, routing=routing):
    obs, st = state.obs, weights["stats"]
    x = {k: (obs[k] - st[k]["mean"]) / st[k]["std"] for k in model.proprio}
    # A DISCOVERSE task's object state is padded to the datasets' width; LIBERO's layout comes padded.
    width = st["object_state"]["mean"].shape[-1] if "object_state" in st else envs.OBJECT_STATE_DIM
    x["object_state"] = (obs["object_state"] if obs["object_state"].shape[-1] == width
                         else envs.padded_object_state(obs["object_state"]))
    if model.normalize_object_state:
      x["object_state"] = (x["object_state"] - st["object_state"]["mean"]) / st["object_state"]["std"]
    if model.use_images:
      for cam in model.cameras:
        x[f"{cam}_rgb"] = obs[f"{cam}_rgb"]
    if model.instruction_vocab:
      x["instruction"] = obs["instruction"]
    pred, r = policy.apply({"params": weights["params"]}, x, routing, method=Policy.predict)
    return pred * st["action"]["std"] + st["action"]["mean"], r

  if temporal and smoothing:
    def init(state):
      b = state.obs["joint_pos"].shape[0]
      return jnp.zeros((b, chunk, chunk, adim), jnp.float32), jnp.zeros((b, model.plug.num_skills), jnp.float32)

    def act(weights, carry, state, t):
      buf, last_r = carry
      _, own = predict(weights, state)
      r = jnp.where(t == 0, own, smoothing * last_r + (1.0 - smoothing) * own)
      pred, _ = predict(weights, state, r)
      action, buf = temporal_ensemble(buf, pred, t, ensemble_k)
      return action, (buf, r), {"routing": r}

    return init, act

  if temporal:
    def init(state):
      b = state.obs["joint_pos"].shape[0]
      return jnp.zeros((b, chunk, chunk, adim), jnp.float32)

    def act(weights, buf, state, t):
      pred, r = predict(weights, state)
      action, buf = temporal_ensemble(buf, pred, t, ensemble_k)
      return action, buf, ({} if r is None else {"routing": r})

    return init, act

  def init(state):
    b = state.obs["joint_pos"].shape[0]
    return jnp.zeros((b, chunk, adim), jnp.float32), jnp.zeros((b, model.plug.num_skills), jnp.float32)

  def act(weights, cs, state, t):
    plan, last_r = cs
    query = t % query_every == 0
    b = plan.shape[0]

    def ask(_):
      pred, r = predict(weights, state)
      return pred, (last_r if r is None else r)

    plan, r = jax.lax.cond(query, ask, lambda _: (plan, last_r), None)
    action = jax.lax.dynamic_index_in_dim(plan, t % query_every, axis=1, keepdims=False)
    info = {"queried": jnp.full((b,), query)}
    if model.is_skillplug:
      info["routing"] = r
    return action, (plan, r), info

  return init, act


def load_controller(run_dir, **kwargs) -> tuple[Controller, object]:
  """The latest checkpoint of a training run as a controller (and its TrainConfig)."""
  from skillplug_jax.train import loop, run_files
  cfg, params, _ = loop.load_params(run_dir)
  stats = run_files.read_stats(run_dir)
  return policy_controller(cfg.model, params, stats, **kwargs), cfg


"""Is the skill library a library? Statistics of the routing and of the skills' features.

Issue 27: at CPU scale the router stayed uniform and the K interactor
outputs settled into opposite groups that the mixture cancels. These are
the numbers that tell such a library from a used one, in every training log
(`training_metrics`, logged as diag/<name>) and every evaluation summary
(`routing_stats` per task, `combine_tasks` across a run's tasks).

Routing, from weights r [..., K] (every query, or every sample of a batch):
usage_entropy, routing_entropy_per_query, effective_skills and mean_weights
(`routing_statistics.routing_stats`, the one implementation and its names), and
  task_skill_mi     I(T; S) in nats, with p(s | t) the mean routing of task
                    t's queries (0: every task routed alike), and
                    task_skill_mi_norm, the same over min(log K, log #tasks).
A used library has low query entropy and high usage entropy: decisive
routing that spreads over the skills.

Geometry, from the interactor's outputs u [B, K, N, D], its input h
[B, N, D] and the fusion weights r [B, K]: signed and absolute cosine
matrices of the token-averaged u_k and of the skill-dependent parts
u_k - h; fused_offset_ratio = |sum_k r_k (u_k - h)| / |h| per token (how
far the plug moves the decoder's input); token_spread = the spread of
u_k - h over the tokens against the norm of its token mean (near 0: the
skill adds one vector to every token, which attention over tokens barely
sees).

All functions are pure and jit-safe; `as_json` turns their results into
plain numbers for the result files.
"""

from __future__ import annotations

import functools
import math
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from skillplug_jax import routing_statistics as routing

_EPS = 1e-12


def entropy(p: jnp.ndarray) -> jnp.ndarray:
  """Shannon entropy (nats) of each distribution p [..., K], as a jax array: `routing.entropy`."""
  return routing.entropy(jnp.asarray(p))


def _normalised_mi(mi, num_skills, num_tasks):
  denom = jnp.minimum(math.log(num_skills), jnp.log(jnp.maximum(num_tasks, 1.0)))
  return jnp.where(num_tasks > 1, mi / jnp.maximum(denom, _EPS), 0.0)


def routing_stats(probs: jnp.ndarray, task_ids: jnp.ndarray | None = None,
                  num_tasks: int | None = None) -> dict:
  """The routing statistics (module docstring) of weights probs [..., K].

  task_ids (the leading shape of probs): each query's task, dense in
  [0, num_tasks) when num_tasks is given; otherwise any integers (they are
  relabelled, jit-safely). With them: task_skill_mi, task_skill_mi_norm,
  num_tasks (those with queries), task_routing [num_tasks, K] (the mean
  routing of each task; zeros for a task without queries) and task_queries.
  """
  num_skills = probs.shape[-1]
  p = jnp.asarray(probs, jnp.float32).reshape(-1, num_skills)
  out = routing.routing_stats(p)
  mean = out["mean_weights"]
  if task_ids is None:
    return out
  ids = jnp.asarray(task_ids).reshape(-1)
  if num_tasks is None:
    num_tasks = ids.shape[0]
    ids = jnp.unique(ids, size=num_tasks, fill_value=ids.min(), return_inverse=True)[1].reshape(-1)
  counts = jax.ops.segment_sum(jnp.ones_like(p[:, 0]), ids, num_tasks)
  per_task = jax.ops.segment_sum(p, ids, num_tasks) / jnp.maximum(counts, 1.0)[:, None]
  p_task = counts / counts.sum()
  # I(T; S) = sum_t p(t) KL(p(s | t) || p(s))
  kl = (per_task * (jnp.log(jnp.clip(per_task, _EPS, 1.0)) - jnp.log(jnp.clip(mean, _EPS, 1.0)))).sum(-1)
  mi = (p_task * kl).sum()
  present = (counts > 0).sum().astype(jnp.float32)
  out.update(task_skill_mi=mi, task_skill_mi_norm=_normalised_mi(mi, num_skills, present),
             num_tasks=present, task_routing=per_task, task_queries=counts)
  return out


def combine_tasks(per_task: Sequence[Mapping]) -> dict:
  """`routing_stats` of a run's queries over all its tasks, from each task's
  own (mean_weights, routing_entropy_per_query, and its number of queries
  under 'queries'): the same numbers as on the concatenated queries, without them."""
  counts = np.asarray([t["queries"] for t in per_task], np.float64)
  means = np.asarray([t["mean_weights"] for t in per_task], np.float64)
  num_skills = means.shape[-1]
  p_task = counts / counts.sum()
  mean = p_task @ means
  h = lambda x: float(entropy(jnp.asarray(x)))  # noqa: E731
  mi = h(mean) - sum(w * h(m) for w, m in zip(p_task, means))
  n = float((counts > 0).sum())
  return dict(usage_entropy=h(mean) / math.log(num_skills),
              routing_entropy_per_query=float(p_task @ np.asarray([t["routing_entropy_per_query"]
                                                                   for t in per_task])),
              effective_skills=math.exp(h(mean)), mean_weights=mean.tolist(),
              task_skill_mi=max(mi, 0.0), task_skill_mi_norm=float(_normalised_mi(max(mi, 0.0), num_skills, n)),
              num_tasks=n, queries=int(counts.sum()))


def _cosines(x: jnp.ndarray) -> jnp.ndarray:
  """Cosine matrix [..., K, K] of the rows of x [..., K, D]."""
  x = x / jnp.maximum(jnp.linalg.norm(x, axis=-1, keepdims=True), 1e-8)
  return jnp.einsum("...kd,...jd->...kj", x, x)


def _off_diagonal_mean(m: jnp.ndarray) -> jnp.ndarray:
  k = m.shape[-1]
  return (m.sum() - jnp.trace(m)) / max(k * (k - 1), 1)


def skill_geometry(u: jnp.ndarray, h: jnp.ndarray, r: jnp.ndarray) -> dict:
  """The geometry (module docstring) of u [B, K, N, D], h [B, N, D], r [B, K].

  Matrices [K, K], averaged over the batch: cos_signed / cos_abs (token-
  averaged u_k), cos_signed_centred / cos_abs_centred (token-averaged
  u_k - h); their off-diagonal means as signed_cos, abs_cos,
  signed_cos_centred, abs_cos_centred; fused_offset_ratio; token_spread.
  """
  u, h, r = (jnp.asarray(a, jnp.float32) for a in (u, h, r))
  c = u - h[:, None]
  out = {}
  for name, x in (("", u), ("_centred", c)):
    cos = _cosines(x.mean(axis=2))
    out[f"cos_signed{name}"] = cos.mean(axis=0)
    out[f"cos_abs{name}"] = jnp.abs(cos).mean(axis=0)
    out[f"signed_cos{name}"] = _off_diagonal_mean(out[f"cos_signed{name}"])
    out[f"abs_cos{name}"] = _off_diagonal_mean(out[f"cos_abs{name}"])
  offset = jnp.einsum("bk,bknd->bnd", r, c)
  out["fused_offset_ratio"] = (jnp.linalg.norm(offset, axis=-1)
                               / jnp.maximum(jnp.linalg.norm(h, axis=-1), 1e-8)).mean()
  token_mean = c.mean(axis=2, keepdims=True)
  spread = jnp.sqrt(((c - token_mean) ** 2).sum(-1).mean(-1))  # [B, K]: rms distance from the mean
  out["token_spread"] = (spread / jnp.maximum(jnp.linalg.norm(token_mean[:, :, 0], axis=-1), 1e-8)).mean()
  return out


def label_skill_mi(probs: jnp.ndarray, labels: jnp.ndarray) -> dict:
  """I(L; S) between each query's label (a mined phase, `train.skill_labels`) and its routing, over
  the queries whose label is in [0, K) (what `losses.router_label_loss` reads; -1: unlabelled):
  label_skill_mi in nats and label_skill_mi_norm over min(log K, log #labels present). Jit-safe."""
  k = probs.shape[-1]
  p = jnp.asarray(probs, jnp.float32).reshape(-1, k)
  ids = jnp.asarray(labels).reshape(-1).astype(jnp.int32)
  w = ((ids >= 0) & (ids < k)).astype(jnp.float32)
  ids = jnp.clip(ids, 0, k - 1)
  counts = jax.ops.segment_sum(w, ids, k)
  per_label = jax.ops.segment_sum(p * w[:, None], ids, k) / jnp.maximum(counts, 1.0)[:, None]
  mean = (p * w[:, None]).sum(0) / jnp.maximum(w.sum(), 1.0)
  kl = (per_label * (jnp.log(jnp.clip(per_label, _EPS, 1.0)) - jnp.log(jnp.clip(mean, _EPS, 1.0)))).sum(-1)
  mi = jnp.maximum((counts / jnp.maximum(counts.sum(), 1.0) * kl).sum(), 0.0)
  present = (counts > 0).sum().astype(jnp.float32)
  return dict(label_skill_mi=mi, label_skill_mi_norm=_normalised_mi(mi, k, present))


def training_metrics(outputs: Mapping[str, jnp.ndarray], task_ids: jnp.ndarray | None = None,
                     labels: jnp.ndarray | None = None) -> dict:
  """The scalar diagnostics of one training batch, as diag_<name> (no gradient).

  The routing statistics and the geometry read the router's weights (what
  the fusion used). task_skill_mi here is a batch estimate (a few queries per task: biased
  upwards); the evaluation's is the one to quote. labels (the batch's `skill_label`, when
  `train.skill_labels` names a labeller): also label_skill_mi(_norm), the routing's information
  about the mined phase, logged whatever `loss.router_label` weighs (0: a diagnostic only).
  """
  out = jax.lax.stop_gradient({k: v for k, v in outputs.items() if k != "pred_actions"})
  tid = None if task_ids is None else jax.lax.stop_gradient(task_ids)
  stats = routing_stats(out["router_probs"], tid)
  names = ["usage_entropy", "routing_entropy_per_query", "effective_skills"]
  names += ["task_skill_mi", "task_skill_mi_norm"] if tid is not None else []
  m = {f"diag_{k}": stats[k] for k in names}
  if labels is not None:
    m.update({f"diag_{k}": v for k, v in label_skill_mi(out["router_probs"], labels).items()})
  if "skill_tokens" in out and "plug_input" in out:
    g = skill_geometry(out["skill_tokens"], out["plug_input"], out["router_probs"])
    for k in ("signed_cos", "abs_cos", "signed_cos_centred", "abs_cos_centred",
              "fused_offset_ratio", "token_spread"):
      m[f"diag_{k}"] = g[k]
  return m


@functools.lru_cache(maxsize=None)
def _features_fn(model_config):
  from skillplug_jax.model.policy import Policy  # the model imports nothing from here
  policy = Policy(model_config)
  return jax.jit(lambda p, o: policy.apply({"params": p}, o, method=Policy.features))


def plug_geometry(model_config, params, obs: Mapping[str, jnp.ndarray]) -> dict:
  """`skill_geometry` of a trained ACT+SkillPlug on a batch of (normalised)
  observations, through the inference path (`Policy.features`), with the
  routing statistics of the same batch under 'routing'."""
  f = _features_fn(model_config)(params, obs)
  return dict(skill_geometry(f["skill_tokens"], f["plug_input"], f["routing"]),
              routing=routing_stats(f["routing"]))


def as_json(tree):
  """Arrays as floats and lists, for the result files."""
  return jax.tree.map(lambda x: np.asarray(x).tolist(), tree)

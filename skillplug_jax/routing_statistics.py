"""Routing statistics, the one implementation and its names: what the router did, in training
logs (`diagnostics.training_metrics`, logged as diag/<name>), evaluation summaries
(`evaluate.protocol`, `evaluate.tables`), the toy problem (`evaluate.toy_rollout`), the probes
and the routing diagnostics of published arrays (`experiments.skill_probes`,
`experiments.routing_diagnostics`, through `evaluate.routing`), and the notebooks. It imports
nothing of the project, so the losses' diagnostics and the evaluation read the same functions
without a loop between them.

The names, from weights r [Q, K] (one row per query, or per sample of a batch):
  routing_entropy_per_query  mean_q H(r_q) / log K    (1: every query uniform, 0: one-hot)
  usage_entropy              H(mean_q r_q) / log K    (1: every skill used alike)
  effective_skills           exp H(mean_q r_q)        (1..K)
  mean_weights               mean_q r_q               [K]
  nmi                        normalised mutual information (arithmetic mean of the
                             entropies, sklearn's default) between argmax_k r_q and a label
                             of each query (the toy: the primitive; nmi_task, nmi_stage,
                             nmi_quadrant against the task, the stage, the robot's quadrant)
Summaries written before these names read through `renamed` (`OLD_NAMES`).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


# Names earlier code wrote for the same numbers (skillplug_jax/diagnostics.py `query_entropy`,
# `mean_routing`; this module's `entropy_frac`; experiments/publish.py `routing_entropy_frac`).
OLD_NAMES = {
    "query_entropy": "routing_entropy_per_query",
    "entropy_frac": "routing_entropy_per_query",
    "routing_entropy_frac": "routing_entropy_per_query",
    "mean_routing": "mean_weights",
    "diag_query_entropy": "diag_routing_entropy_per_query",
    "diag/query_entropy": "diag/routing_entropy_per_query",
}
# Old numbers in nats, read as today's fraction of log K (K from the row's mean weights).
_OLD_NATS = {"entropy": "routing_entropy_per_query", "entropy_of_mean": "usage_entropy"}


def renamed(summary: Any) -> Any:
  """A summary (any JSON: a published summary.json, routing diagnostics, one result) written with
  the old key names, with today's: each of `OLD_NAMES` renamed wherever it occurs, and an old
  routing summary's nats (`entropy_of_mean`, `entropy` beside `entropy_frac`) as today's fractions
  of log K (K: the length of its mean weights). A key present under both names keeps the new one."""
  if isinstance(summary, list):
    return [renamed(x) for x in summary]
  if not isinstance(summary, dict):
    return summary
  out = {OLD_NAMES.get(k, k): renamed(v) for k, v in summary.items() if OLD_NAMES.get(k, k) == k}
  for k, v in summary.items():
    if OLD_NAMES.get(k, k) != k:
      out.setdefault(OLD_NAMES[k], renamed(v))
  weights = out.get("mean_weights")
  if "entropy_of_mean" in out and isinstance(weights, list) and len(weights) > 1:
    out.setdefault("usage_entropy", out.pop("entropy_of_mean") / math.log(len(weights)))
    if "entropy_frac" in summary:
      out.pop("entropy", None)  # nats: the fraction is routing_entropy_per_query
  return out


def entropy(p):
  """Shannon entropy (nats) of each distribution p [..., K]. A jax array (inside jit, in training)
  gives a jax array, float32, with a finite gradient at p = 0; anything else numpy float64."""
  xp = jnp if isinstance(p, jax.Array) else np
  p = xp.asarray(p, xp.float32 if xp is jnp else np.float64)
  return -(p * xp.log(xp.clip(p, 1e-12, 1.0))).sum(-1)


def routing_stats(weights) -> dict:
  """The statistics of weights [..., K] (every leading axis a query): routing_entropy_per_query,
  usage_entropy, effective_skills, mean_weights (module docstring). jit-safe on jax arrays (the
  values are then jax arrays); plain floats and a list otherwise."""
  xp = jnp if isinstance(weights, jax.Array) else np
  weights = weights if xp is jnp else np.asarray(weights, np.float64)
  k = weights.shape[-1]
  r = weights.reshape(-1, k)
  mean = r.mean(0)
  h_mean = entropy(mean)
  out = dict(routing_entropy_per_query=entropy(r).mean() / math.log(k), usage_entropy=h_mean / math.log(k),
             effective_skills=xp.exp(h_mean), mean_weights=mean)
  if xp is np:
    out = {n: (v.tolist() if n == "mean_weights" else float(v)) for n, v in out.items()}
  return out


def nmi(x, y) -> float:
  """Normalised mutual information of two label arrays: I(x; y) / ((H(x) + H(y)) / 2).

  1 for a one-to-one mapping, ~0 for independent labels; 0 when both are constant.
  """
  x, y = np.asarray(x).ravel(), np.asarray(y).ravel()
  _, xi = np.unique(x, return_inverse=True)
  _, yi = np.unique(y, return_inverse=True)
  joint = np.zeros((xi.max() + 1, yi.max() + 1))
  np.add.at(joint, (xi, yi), 1.0)
  joint /= joint.sum()
  px, py = joint.sum(1), joint.sum(0)
  nz = joint > 0
  mi = float((joint[nz] * np.log(joint[nz] / (px[:, None] * py[None, :])[nz])).sum())
  hx, hy = float(entropy(px)), float(entropy(py))
  return 0.0 if hx + hy <= 0 else max(0.0, mi / (0.5 * (hx + hy)))

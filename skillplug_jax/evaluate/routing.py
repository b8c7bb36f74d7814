"""What the router did: statistics of the per-query routing arrays (`protocol.write_routing`).

Is the skill library used? Routing that stays uniform (entropy near log K
at every query, on every task) means the fused feature is the plain mean of
the K interactor outputs, and the skills cannot specialise by task; routing
that differs between tasks, or moves within an episode, is what the paper's
claim needs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from skillplug_jax.evaluate.protocol import read_routing


def queries_of(routing: np.ndarray) -> np.ndarray:
  """[trials, steps, K] (NaN where no query) -> [queries, K], every query of every trial."""
  flat = routing.reshape(-1, routing.shape[-1])
  return flat[~np.isnan(flat[:, 0])]


def entropy(weights: np.ndarray) -> np.ndarray:
  """Shannon entropy (nats) of each row of weights [..., K] (rows sum to 1)."""
  w = np.clip(weights, 1e-12, 1.0)
  return -(w * np.log(w)).sum(-1)


def summarise_task(data: dict) -> dict:
  """One task's routing: mean weights, mean per-query entropy (nats and as a fraction of log K),
  the entropy of the mean weights, the largest weight, and the spread of the weights within
  episodes (mean over trials of each skill's std over the episode's queries)."""
  q = queries_of(data["routing"])
  k = q.shape[-1]
  h = entropy(q)
  within = [np.std(r[~np.isnan(r[:, 0])], axis=0).mean() for r in data["routing"] if (~np.isnan(r[:, 0])).sum() > 1]
  succ = data["success"]
  per_trial_mean = np.stack([np.nanmean(r, axis=0) for r in data["routing"]])
  out = dict(task=data["task"], queries=int(q.shape[0]), mean_weights=q.mean(0).tolist(),
             entropy=float(h.mean()), entropy_frac=float(h.mean() / np.log(k)),
             entropy_of_mean=float(entropy(q.mean(0))), max_weight=float(q.max(-1).mean()),
             within_episode_std=float(np.mean(within)) if within else None,
             success_rate=float(succ.mean()))
  if succ.any() and (~succ).any():  # do solved and failed trials route differently?
    out["mean_weights_success"] = per_trial_mean[succ].mean(0).tolist()
    out["mean_weights_failure"] = per_trial_mean[~succ].mean(0).tolist()
  return out


def summarise_files(paths: Iterable[str | Path]) -> list[dict]:
  return [dict(summarise_task(read_routing(p)), file=str(p)) for p in paths]


def between_task_distance(summaries: list[dict]) -> np.ndarray:
  """Total-variation distance between the tasks' mean routing weights [tasks, tasks]:
  0 everywhere means every task is routed alike."""
  m = np.asarray([s["mean_weights"] for s in summaries])
  return 0.5 * np.abs(m[:, None, :] - m[None, :, :]).sum(-1)

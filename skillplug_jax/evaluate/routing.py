"""What the router did in closed loop: summaries of the per-query routing arrays
(`protocol.write_routing`), per task and between tasks.

Is the skill library used? Routing that stays uniform (entropy near log K
at every query, on every task) means the fused feature is the plain mean of
the K interactor outputs, and the skills cannot specialise by task; routing
that differs between tasks, or moves within an episode, is what the paper's
claim needs. The statistics themselves, and their names, are
`skillplug_jax.routing_statistics` (re-exported here).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from skillplug_jax.routing_statistics import OLD_NAMES, entropy, nmi, renamed, routing_stats  # noqa: F401


def queries_of(routing: np.ndarray) -> np.ndarray:
  """[trials, steps, K] (NaN where no query) -> [queries, K], every query of every trial."""
  flat = routing.reshape(-1, routing.shape[-1])
  return flat[~np.isnan(flat[:, 0])]


def summarise_task(data: dict) -> dict:
  """One task's routing (`routing_stats` of its queries), the largest weight, and the spread of
  the weights within episodes (mean over trials of each skill's std over the episode's queries)."""
  q = queries_of(data["routing"]).astype(np.float64)
  within = [np.std(r[~np.isnan(r[:, 0])], axis=0).mean() for r in data["routing"] if (~np.isnan(r[:, 0])).sum() > 1]
  succ = data["success"]
  per_trial_mean = np.stack([np.nanmean(r, axis=0) for r in data["routing"]])
  out = dict(task=data["task"], queries=int(q.shape[0]), **routing_stats(q), max_weight=float(q.max(-1).mean()),
             within_episode_std=float(np.mean(within)) if within else None,
             success_rate=float(succ.mean()))
  if succ.any() and (~succ).any():  # do solved and failed trials route differently?
    out["mean_weights_success"] = per_trial_mean[succ].mean(0).tolist()
    out["mean_weights_failure"] = per_trial_mean[~succ].mean(0).tolist()
  return out


def summarise_files(paths: Iterable[str | Path]) -> list[dict]:
  from skillplug_jax.evaluate.protocol import read_routing  # protocol writes its summaries with this module
  return [dict(summarise_task(read_routing(p)), file=str(p)) for p in paths]


def between_task_distance(summaries: list[dict]) -> np.ndarray:
  """Total-variation distance between the tasks' mean routing weights [tasks, tasks]:
  0 everywhere means every task is routed alike."""
  m = np.asarray([s["mean_weights"] for s in summaries])
  return 0.5 * np.abs(m[:, None, :] - m[None, :, :]).sum(-1)

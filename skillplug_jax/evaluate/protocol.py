"""The evaluation protocol: paired seeded trials per task, every policy, every training seed.

Trial i of a task starts from `rollout.reset_keys(seed, trials)[i]` for every
policy evaluated, so two policies are compared on the same initial states.
The default seed (1000) is far from the demonstrations' (0): evaluation
starts are not training starts.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Sequence

import jax
import numpy as np
from tqdm import tqdm

import envs
from envs import rollout as env_rollout
from skillplug_jax.evaluate import tables
from skillplug_jax.evaluate.policy_controller import load_controller
from skillplug_jax.evaluate.rollout import Controller, EpisodeResults, evaluate

EVAL_SEED = 1000


def trial_keys(seed: int, trials: int) -> jax.Array:
  return env_rollout.reset_keys(seed, trials)


def evaluate_task(task: str, controller: Controller, trials: int, seed: int = EVAL_SEED, batch: int = 50,
                  render: bool = False, image_size=(64, 64)) -> dict:
  """Success rate and query counts of one controller on one task."""
  n_env = min(batch, trials)
  benv = envs.make(task, num_envs=n_env, render=render, image_size=image_size)
  keys = trial_keys(seed, trials)
  parts: list[EpisodeResults] = []
  for start in range(0, trials, n_env):
    k = keys[start:start + n_env]
    if k.shape[0] < n_env:  # last partial batch: pad with repeats, drop them after
      k = jax.numpy.concatenate([k, keys[:n_env - k.shape[0]]])
    parts.append(evaluate(benv, controller, k))
  take = lambda f: np.concatenate([getattr(p, f) for p in parts])[:trials]  # noqa: E731
  success, nan, queries = take("success"), take("nan"), take("queries")
  routing = [p.routing for p in parts if p.routing is not None]
  return dict(task=task, abbr=benv.env.abbr, trials=trials, seed=seed,
              success_rate=float(success.mean()), successes=int(success.sum()),
              nan_episodes=int(nan.sum()),
              mean_queries_success=float(queries[success].mean()) if success.any() else None,
              mean_steps_success=float(take("first_success_step")[success].mean()) if success.any() else None,
              mean_routing=(np.nanmean(np.concatenate([r.reshape(-1, r.shape[-1]) for r in routing]), axis=0)
                            .tolist() if routing else None))


def evaluate_runs(run_dirs: Sequence[str | Path], tasks: Sequence[str], trials: int, seed: int = EVAL_SEED,
                  batch: int = 50, query_every: int = 1, progress: bool = True) -> dict:
  """Every run on every task; runs of the same policy label are that policy's training seeds."""
  results, rates = [], {}
  bar = tqdm(total=len(run_dirs) * len(tasks), desc="eval", unit="task", file=sys.stderr,
             disable=not progress)
  for run in run_dirs:
    controller, cfg = load_controller(run, query_every=query_every)
    label = "ACT+SkillPlug" if cfg.model.is_skillplug else "ACT"
    h, w = cfg.model.image_size
    for task in tasks:
      bar.set_postfix_str(f"{label} seed {cfg.seed} {task}")
      t0 = time.time()
      r = evaluate_task(task, controller, trials, seed, batch, render=cfg.model.use_images, image_size=(w, h))
      r.update(run=str(run), policy=label, train_seed=cfg.seed, preset=cfg.preset, wall_s=round(time.time() - t0, 1))
      results.append(r)
      rates.setdefault(label, {}).setdefault(task, []).append(r["success_rate"])
      bar.update(1)
  bar.close()
  table = tables.success_table(rates, tasks)
  queries = {}
  for label in rates:
    qs = [r["mean_queries_success"] for r in results if r["policy"] == label and r["mean_queries_success"]]
    queries[label] = float(np.mean(qs)) if qs else None
  return dict(trials=trials, seed=seed, query_every=query_every, device=str(jax.devices()[0]),
              results=results, table=table, mean_queries_per_success=queries)

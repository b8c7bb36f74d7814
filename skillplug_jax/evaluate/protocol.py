"""The evaluation protocol: paired seeded trials per task, every policy, every training seed.

Trial i of a task starts from `rollout.reset_keys(seed, trials)[i]` for every
policy evaluated, so two policies are compared on the same initial states.
The default seed (1000) is far from the demonstrations' (0): evaluation
starts are not training starts. appearance="shifted" (ours) draws trial i's
cameras in its own colours and light, drawn from its reset key
(`envs.appearance`): the same trials, paired with the default appearance's,
with only the pixels changed.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Sequence

import jax
import numpy as np
from tqdm import tqdm

import envs
from envs import rollout as env_rollout
from envs.rollout import Controller, EpisodeResults, local_devices_for, run_episodes
from envs.env import SOLVER_LIMIT_BITS, solver_limit_counts
from skillplug_jax import diagnostics, experiment
from skillplug_jax.evaluate import groups, tables
from skillplug_jax.evaluate.policy_controller import load_controller

EVAL_SEED = 1000
VIDEO_SIZE = (128, 128)  # (H, W) of side-camera videos of state-based policies (image policies: their own size)


def trial_keys(seed: int, trials: int) -> jax.Array:
  return env_rollout.reset_keys(seed, trials)


def evaluate_task(task: str, controller: Controller, trials: int, seed: int = EVAL_SEED, batch: int = 50,
                  render: bool = False, image_size=(64, 64), videos: int = 0,  # image_size: (H, W)
                  video_dir: str | Path | None = None, backend: str = "auto",
                  routing_file: str | Path | None = None, on_batch=None, appearance: str = "default") -> dict:
  """Success rate and query counts of one controller on one task.

  Memory is bounded by `batch`, not `trials`: `batch` environments run at a
  time and only per-trial outcomes (and, for ACT+SkillPlug, routing weights)
  are kept between batches. Trial i's start depends on (seed, i) alone, so
  the first trials of a longer evaluation are those of a shorter one, at any
  batch size. on_batch(n): called after each batch with the trials it added
  (a progress bar's update).

  Besides the means, `trial_success` and `trial_queries` keep trial i's
  outcome and query count (trial i: the same start for every policy), for
  the paired tables.

  The batch is split over the local devices (GPUs only, when rendering: see
  `rollout.local_devices_for`). videos > 0 writes the side
  camera of the first `videos` trials to `video_dir/<task>_trialNN.gif`.
  routing_file: write every query's routing weights there (`write_routing`;
  ACT+SkillPlug only). appearance: "default" or "shifted" (`envs.appearance`:
  trial i's look depends on (seed, i) alone; videos show it too). A
  controller that reads cameras (`Controller.image_size`) is drawn at its
  own size whatever `render` says; an `image_size` that differs is an error.
  The API's edge: a `backend` of "auto" is resolved here, once.
  """
  backend = envs.resolve_backend(backend)
  envs.appearance.check(appearance)
  if getattr(controller, "instruction", None) is not None:
    raise ValueError(f"this policy reads its task's instruction, and {task} has none (our DISCOVERSE tasks "
                     "come without language; LIBERO's have it)")
  needs = getattr(controller, "image_size", None)
  if needs is not None:  # an image policy: drawn at its own size, even where a caller forgot to ask
    if render and tuple(image_size) != tuple(needs):
      raise ValueError(f"this policy reads {needs[0]}x{needs[1]} camera images; "
                       f"cannot evaluate it on {image_size[0]}x{image_size[1]} ones")
    render, image_size = True, tuple(needs)
  devices = local_devices_for(min(batch, trials), render=render or videos > 0, backend=backend)
  ndev = 1 if devices is None else len(devices)
  per_device = -(-min(batch, trials) // ndev)
  n_env = per_device * ndev
  benv = envs.make(task, num_envs=per_device, render=render, image_size=image_size, devices=devices,
                   backend=backend, appearance=appearance)
  keys = trial_keys(seed, trials)
  parts: list[EpisodeResults] = []
  video_env = None
  for start in range(0, trials, n_env):
    k = keys[start:start + n_env]
    if k.shape[0] < n_env:  # last partial batch: pad with repeats, drop them after
      k = jax.numpy.concatenate([k, keys[:n_env - k.shape[0]]])
    frames = min(videos, per_device) if start == 0 else 0
    if frames:  # the first batch again with the side camera on (a state policy renders nothing)
      video_env = benv if render else envs.make(task, num_envs=per_device, render=True, image_size=VIDEO_SIZE,
                                                devices=devices, backend=backend, appearance=appearance)
      parts.append(run_episodes(video_env, controller, k, devices, frames=frames))
      write_videos(parts[-1].frames, Path(video_dir or "."), task)
    else:
      parts.append(run_episodes(benv, controller, k, devices))
    if on_batch is not None:
      on_batch(min(n_env, trials - start))
  take = lambda f: np.concatenate([getattr(p, f) for p in parts])[:trials]  # noqa: E731
  success, nan, queries = take("success"), take("nan"), take("queries")
  overflow = take("overflow") if all(p.overflow is not None for p in parts) else np.zeros(trials, np.int32)
  routing = [p.routing for p in parts if p.routing is not None]
  if routing_file is not None and routing:
    write_routing(routing_file, task, routing, trials, success, take("first_success_step"), queries)
  return dict(task=task, abbr=benv.env.abbr, trials=trials, seed=seed, devices=ndev, backend=backend,
              renderer=benv.renderer, appearance=appearance, render_s=_render_seconds(benv, None if video_env is benv else video_env),
              success_rate=float(success.mean()), successes=int(success.sum()),
              nan_episodes=int(nan.sum()), solver_limit_episodes=solver_limit_counts(overflow),
              mean_queries_success=float(queries[success].mean()) if success.any() else None,
              mean_steps_success=float(take("first_success_step")[success].mean()) if success.any() else None,
              mean_weights=(np.nanmean(np.concatenate([r.reshape(-1, r.shape[-1]) for r in routing]), axis=0)
                            .tolist() if routing else None),
              trial_success=success.tolist(), trial_queries=queries.tolist(),
              trial_success_step=take("first_success_step").tolist(),
              **({"diagnostics": routing_diagnostics(routing, trials)} if routing else {}))


def _render_seconds(*benvs) -> float | None:
  """Wall seconds the environments spent drawing cameras (the rendering share of an evaluation);
  None where a backend draws inside its jitted step (MJX), so that it cannot be timed apart."""
  times = [b.render_s for b in benvs if b is not None and b.render]
  return None if any(t is None for t in times) else round(sum(times), 2)


def routing_diagnostics(parts: Sequence[np.ndarray], trials: int) -> dict:
  """`diagnostics.routing_stats` of every query of the first `trials` trials
  (parts: [steps, envs, K] per batch of episodes, NaN where no query), and
  their number under 'queries' (what `diagnostics.combine_tasks` weights by)."""
  steps = max(p.shape[0] for p in parts)
  padded = [np.pad(p, ((0, steps - p.shape[0]), (0, 0), (0, 0)), constant_values=np.nan) for p in parts]
  flat = np.concatenate(padded, axis=1)[:, :trials].reshape(-1, parts[0].shape[-1])
  q = flat[~np.isnan(flat[:, 0])]
  if not len(q):
    return {"queries": 0}
  return dict(diagnostics.as_json(diagnostics.routing_stats(q)), queries=int(len(q)))


def write_routing(path: str | Path, task: str, parts: Sequence[np.ndarray], trials: int, success: np.ndarray,
                  first_success_step: np.ndarray, queries: np.ndarray) -> None:
  """The router's weights at every query of every trial, with each trial's outcome (one .npz).

  routing [trials, steps, K] float16: trial i's weights at control step t,
  NaN where it made no query (every step after its episode ended, and
  between queries with open-loop chunks); success [trials], first_success_step
  [trials] (-1: none), queries [trials]; task, the task's name. Trial i is
  the same initial state for every policy (`trial_keys`). Written atomically.
  """
  steps = max(p.shape[0] for p in parts)
  padded = [np.pad(p, ((0, steps - p.shape[0]), (0, 0), (0, 0)), constant_values=np.nan) for p in parts]
  routing = np.concatenate(padded, axis=1)[:, :trials].transpose(1, 0, 2).astype(np.float16)
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.with_name(path.name + ".tmp")
  with open(tmp, "wb") as f:
    np.savez_compressed(f, routing=routing, success=np.asarray(success, bool),
                        first_success_step=np.asarray(first_success_step, np.int32),
                        queries=np.asarray(queries, np.int32), task=np.asarray(task))
  os.replace(tmp, path)


def read_routing(path: str | Path) -> dict:
  """`write_routing`'s arrays as a dict (routing as float32)."""
  with np.load(path) as z:
    out = {k: z[k] for k in z.files}
  out["routing"] = out["routing"].astype(np.float32)
  out["task"] = str(out["task"])
  return out


def write_videos(frames: list, out: Path, task: str, fps: int = 20) -> None:
  import imageio.v3 as iio
  out.mkdir(parents=True, exist_ok=True)
  for i, video in enumerate(frames):
    path = out / f"{task}_trial{i:02d}.gif"
    tmp = path.with_suffix(".tmp.gif")
    iio.imwrite(tmp, video, duration=1000 / fps, loop=0)
    os.replace(tmp, path)


def evaluate_runs(run_dirs: Sequence[str | Path], tasks: Sequence[str], trials: int, seed: int = EVAL_SEED,
                  batch: int = 50, query_every: int = 1, progress: bool = True, videos: int = 0,
                  video_dir: str | Path = "videos", backend: str = "auto", appearance: str = "default",
                  routing_smoothing: float = 0.0) -> dict:
  """Every run on every task, and the tables (`tables.summarise`).

  Runs whose training configurations differ only in the seed (and where
  they were written) are one row's training seeds; any other difference
  makes another row, named by its overrides against the run's record
  (`experiment.read_record`). videos > 0: GIFs of each run's first trials in
  video_dir/<run name>/. appearance: "default" or "shifted" (`evaluate_task`). routing_smoothing:
  `policy_controller`'s (ours; 0: the router's own weights). The API's edge: a
  `backend` of "auto" is resolved here, once, and passed down.
  """
  backend = envs.resolve_backend(backend)
  envs.appearance.check(appearance)  # before any run is loaded
  results = []
  # Every run is loaded first: a missing or damaged checkpoint fails before any evaluation.
  smooth = dict(routing_smoothing=routing_smoothing) if routing_smoothing else {}
  loaded = [(run, *load_controller(run, query_every=query_every, **smooth)) for run in run_dirs]
  records = {run: experiment.read_record(run) for run in run_dirs}
  for run, _, cfg in loaded:
    warn_if_other_renderer(run, cfg, backend)
  bar = tqdm(total=len(run_dirs) * len(tasks) * trials, desc="eval", unit="trial", file=sys.stderr,
             disable=not progress, dynamic_ncols=True)
  for run, controller, cfg in loaded:
    row = groups.row_fields(cfg, records[run])
    for task in tasks:
      bar.set_postfix_str(f"{row['policy']} seed {cfg.seed} {task}")
      t0 = time.time()
      r = evaluate_task(task, controller, trials, seed, batch, render=cfg.model.use_images,
                        image_size=cfg.model.image_size, videos=videos, video_dir=Path(video_dir) / Path(run).name,
                        backend=backend, on_batch=bar.update, appearance=appearance)
      r.update(run=str(run), **row, trained_on=cfg.backend, wall_s=round(time.time() - t0, 1))
      results.append(r)
  bar.close()
  return dict(trials=trials, seed=seed, query_every=query_every, routing_smoothing=routing_smoothing,
              device=str(jax.devices()[0]),
              backend=backend, appearance=appearance, results=results, **tables.summarise(results, tasks))


def warn_if_other_renderer(run, cfg, backend: str) -> None:
  """An image policy sees another renderer's pixels when evaluated on another backend:
  MuJoCo Warp's ray caster and OpenGL draw the same scene differently."""
  if not cfg.model.use_images:
    return
  trained, now = envs.renderer_of(cfg.backend), envs.renderer_of(backend)
  if trained != now:
    print(f"WARNING: {run} is an image policy trained on {trained} images ({cfg.backend} backend) and is "
          f"evaluated on {now} images ({backend} backend); the renderers draw different pixels, so its "
          f"success rates measure transfer between renderers too", file=sys.stderr)


def solver_limit_summary(results: Sequence[dict]) -> str:
  """One line for a whole run: how many episodes hit the solver's or its line search's limit."""
  total = sum(r["trials"] for r in results)
  hit = {k: sum(r["solver_limit_episodes"][k] for r in results) for k in SOLVER_LIMIT_BITS}
  return (f"The constraint solver stopped at its iteration limit in {hit['solver_iterations']} and its "
          f"line search (MuJoCo Warp only) in {hit['linesearch_iterations']} of {total} episodes "
          "(per task in the JSON)")

"""One task's paired closed-loop trials, on whichever benchmark the task belongs to.

Our DISCOVERSE tasks run `protocol.evaluate_task` (trial i: the start drawn from (seed, i), on
either physics backend); LIBERO's run `evaluate.libero.evaluate_task` (trial i: the benchmark's
init state i, on the C engine). Both return the same fields the tables read (`success_rate`,
`trial_success`, `trial_queries`, the routing diagnostics), so the pipeline and `skillplug
fewshot` tabulate either.
"""

from __future__ import annotations

from pathlib import Path

from envs.libero import suites as libero_suites
from envs.rollout import Controller
from skillplug_jax.evaluate import libero, protocol


def evaluate_task(task: str, controller: Controller, cfg, trials: int, seed: int = protocol.EVAL_SEED,
                  batch: int = 50, backend: str = "mujoco", routing_file: str | Path | None = None,
                  videos: int = 0, video_dir: str | Path | None = None) -> dict:
  """`trials` paired trials of `controller` (trained by `cfg`, a TrainConfig) on `task`; videos > 0:
  GIFs of the first trials in `video_dir`."""
  if libero_suites.is_libero(task):
    if trials > libero_suites.INIT_STATES_PER_TASK:
      raise ValueError(f"{task}: LIBERO has {libero_suites.INIT_STATES_PER_TASK} init states per task; "
                       f"cannot run {trials} paired trials")
    if backend != "mujoco":
      raise ValueError(f"{task}: LIBERO's trials run on MuJoCo's C engine only (backend 'mujoco'), not {backend!r}")
    return dict(libero.evaluate_task(task, controller, trials, videos, video_dir, routing_file=routing_file),
                seed=None, backend=backend)
  return protocol.evaluate_task(task, controller, trials, seed, batch, render=cfg.model.use_images,
                                image_size=cfg.model.image_size, videos=videos, video_dir=video_dir,
                                routing_file=routing_file, backend=backend)

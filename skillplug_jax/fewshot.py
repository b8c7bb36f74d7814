"""Few-shot adaptation: one fine-tune per unseen task from a multi-task run, then its evaluation.

The protocol (which groups train, for how many steps) is the source run's
experiment config's `fewshot` (experiments/configs/): by the paper,
ACT+SkillPlug retrains the router and the action head (encoder, skill
library, interactor and posterior frozen), ACT the action head only. Both
are the ordinary training loop with an optax mask (`TrainConfig.trainable`)
and the multi-task parameters as the starting point (`TrainConfig.init_from`).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Sequence

import envs
from skillplug_jax.evaluate import groups, protocol, tables
from skillplug_jax.evaluate.policy_controller import load_controller
from skillplug_jax.train import checkpoint, loop
from skillplug_jax.train.config import TrainConfig


def source_protocol(source: TrainConfig):
  """The few-shot protocol (`configs.FewShot`) of the config a multi-task run was trained from."""
  from experiments import configs  # the configs build on this package: load them when asked
  try:
    return configs.get(source.preset).fewshot
  except ValueError as e:
    raise ValueError(f"the run's config {source.preset!r} is not in experiments/configs/, so its few-shot "
                     f"protocol is unknown: {e}") from e


def fewshot_config(source: TrainConfig, source_dir: Path, task: str, taskset: str, demos: int,
                   steps: int | None = None, trainable: Sequence[str] | None = None) -> TrainConfig:
  """The fine-tune of `source` on `task`; steps and trainable groups default to its config's protocol."""
  protocol = source_protocol(source) if steps is None or trainable is None else None
  steps = protocol.steps if steps is None else steps
  trainable = protocol.trainable(source.model.policy) if trainable is None else tuple(sorted(trainable))
  return dataclasses.replace(
      source, taskset=task, data_taskset=taskset, demos=demos, init_from=str(source_dir),
      trainable=trainable, max_steps=steps,
      warmup_steps=min(source.warmup_steps, max(steps // 10, 0)),
      ckpt_every=max(steps, 1) if steps else source.ckpt_every,
      workdir=str(Path(f"{source_dir}_fewshot") / task))


def adapt_and_evaluate(source_runs: Sequence[str | Path], taskset: str = "discoverse_fewshot4",
                       demos: int = 10, trials: int = 50, seed: int = protocol.EVAL_SEED,
                       batch: int = 50, steps: int | None = None, progress: bool = True,
                       backend: str = "auto") -> dict:
  """Fine-tune every source run on every task of `taskset`, evaluate, tabulate.

  Rows are the source runs' training configurations (`groups`): the
  few-shot settings are the same for every row of one call, and the seeds
  of one source configuration are one row.
  """
  tasks = envs.taskset(taskset)
  results = []
  for src in source_runs:
    src = Path(src)
    source = checkpoint.read_config(src)
    label = groups.policy_label(source)
    for task in tasks:
      cfg = fewshot_config(source, src, task, taskset, demos, steps)
      if progress:
        print(f"few-shot {label} (seed {source.seed}) on {task}: training {sorted(cfg.trainable)}",
              file=sys.stderr)
      run = loop.train(cfg, progress=progress)
      controller, _ = load_controller(run)
      protocol.warn_if_other_renderer(run, cfg, backend)
      r = protocol.evaluate_task(task, controller, trials, seed, batch, render=cfg.model.use_images,
                                 image_size=cfg.model.image_size, backend=backend)
      r.update(run=str(run), source=str(src), policy=label, train_seed=source.seed,
               config=groups.training_key(source), trainable=list(cfg.trainable), steps=cfg.max_steps,
               trained_on=source.backend)
      results.append(r)
  return dict(taskset=taskset, demos=demos, trials=trials, seed=seed, backend=envs.resolve_backend(backend),
              results=results,
              **tables.summarise(results, tasks))

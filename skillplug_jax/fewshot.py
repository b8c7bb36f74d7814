"""Few-shot adaptation: one fine-tune per unseen task from a multi-task run, then its evaluation.

The protocol (which groups train, for how many steps) is the one the source
run recorded of its experiment config (`RunRecord.fewshot`, `experiment.read_record`), not
today's config file's. By the paper, ACT+SkillPlug retrains the router and
the action head (encoder, skill library, interactor and posterior frozen),
ACT the action head only (`FewShot.trainable`). Both are the ordinary training
loop with an optax mask (`TrainConfig.trainable`) and the multi-task parameters as the starting
point (`TrainConfig.init_from`); a fine-tune keeps its source's record.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Sequence

import envs
from skillplug_jax import experiment
from skillplug_jax.evaluate import groups, protocol, tables
from skillplug_jax.evaluate import trials as trials_of
from skillplug_jax.evaluate.policy_controller import load_controller
from skillplug_jax.experiment import FewShot, Trainable
from skillplug_jax.train import config as train_config
from skillplug_jax.train import loop, run_files
from skillplug_jax.train.config import TrainConfig


def units(plan: FewShot) -> list[tuple[str, tuple[str, ...]]]:
  """(what one fine-tune trains on, the tasks it is evaluated on) for each fine-tune of `plan`:
  each task of its taskset (`per="task"`), or each comma-separated part of it, all of that part's
  tasks at once (`per="taskset"`: a LIBERO suite)."""
  from envs import toy_skills  # the toy's tasksets (envs/toy_skills.py) are not the tabletop's

  def tasks(part: str) -> tuple[str, ...]:
    return tuple(toy_skills.TASKSETS.get(part) or envs.taskset(part))

  if plan.per == "taskset":
    return [(part, tasks(part)) for part in plan.taskset.split(",")]
  return [(t, (t,)) for part in plan.taskset.split(",") for t in tasks(part)]


def fewshot_config(source: TrainConfig, source_dir: Path, task: str, plan: FewShot, variant: str = "") -> TrainConfig:
  """The fine-tune of `source` on `task` (a unit of `plan`: one of its tasks, or one of its parts
  with `per="taskset"`) by the few-shot protocol `plan`:
  the one the source run recorded (`experiment.read_record`), or one the caller chose. `variant`
  names a departure from the recorded protocol: its fine-tunes go to `RUN_fewshot_<variant>/`.
  `plan.train_overrides` (TrainConfig `key=value`) are applied last, to the fine-tune alone."""
  steps = plan.steps
  loss, folder = source.loss, f"{source_dir}_fewshot" + (f"_{variant}" if variant else "")
  if not plan.marginal_terms:  # one task's batch: no pressure to spread it over the skills
    loss = dataclasses.replace(loss, usage=0.0)
    folder += "_no_marginal_terms"  # beside the default protocol's fine-tunes, not resuming them
  cfg = dataclasses.replace(
      source, taskset=task, data_taskset=plan.taskset, demos=plan.demos, init_from=str(source_dir),
      trainable=plan.trainable.of(source.model.policy), max_steps=steps, loss=loss,
      warmup_steps=min(source.warmup_steps, max(steps // 10, 0)),
      ckpt_every=max(steps, 1) if steps else source.ckpt_every,
      workdir=str(Path(folder) / task))
  return train_config.override(cfg, plan.train_overrides) if plan.train_overrides else cfg


def adapt_and_evaluate(source_runs: Sequence[str | Path], taskset: str = "discoverse_fewshot4",
                       demos: int = 10, trials: int = 50, seed: int = protocol.EVAL_SEED,
                       batch: int = 50, steps: int | None = None, progress: bool = True,
                       backend: str = "auto", marginal_terms: bool | None = None,
                       trainable: Sequence[str] | None = None, per: str | None = None) -> dict:
  """Fine-tune every source run on every task of `taskset`, evaluate, tabulate.

  Rows are the source runs' training configurations (`groups`): the
  few-shot settings are the same for every row of one call, and the seeds
  of one source configuration are one row. `steps`, `marginal_terms` and
  `trainable` (the parameter groups fine-tuned, for either policy) and `per` (`FewShot.per`): None
  keeps what the source run recorded (`FewShot`). Groups other than the
  recorded ones fine-tune into `RUN_fewshot_train-<groups>/`. The API's edge:
  a `backend` of "auto" (evaluation's physics) is resolved here, once.
  """
  backend = envs.resolve_backend(backend)
  tasks = [t for part in taskset.split(",") for t in envs.taskset(part)]
  results = []
  for src in source_runs:
    src = Path(src)
    source, record = run_files.read_config(src), experiment.read_record(src)
    label = groups.policy_label(source)
    chosen = dataclasses.replace(
        record.fewshot, taskset=taskset, demos=demos, steps=record.fewshot.steps if steps is None else steps,
        marginal_terms=record.fewshot.marginal_terms if marginal_terms is None else marginal_terms,
        per=record.fewshot.per if per is None else per)
    variant = ""
    if trainable is not None and tuple(sorted(trainable)) != chosen.trainable.of(source.model.policy):
      chosen = dataclasses.replace(chosen, trainable=Trainable(act=tuple(trainable), skillplug=tuple(trainable)))
      variant = "train-" + "+".join(sorted(trainable))
    for unit, unit_tasks in units(chosen):
      cfg = fewshot_config(source, src, unit, chosen, variant)
      if progress:
        print(f"few-shot {label} (seed {source.seed}) on {unit}: training {sorted(cfg.trainable)}",
              file=sys.stderr)
      run = loop.train(cfg, progress=progress, record=record)
      controller, _ = load_controller(run)
      protocol.warn_if_other_renderer(run, cfg, backend)
      for task in unit_tasks:
        r = trials_of.evaluate_task(task, controller, cfg, trials, seed, batch, backend=backend)
        r.update(run=str(run), source=str(src), **groups.row_fields(source, record),
                 trainable=list(cfg.trainable), steps=cfg.num_steps(demos * len(unit_tasks)),
                 trained_on=source.backend, fewshot_loss=dict(usage=cfg.loss.usage))
        results.append(r)
  return dict(taskset=taskset, demos=demos, trials=trials, seed=seed, backend=backend,
              results=results,
              **tables.summarise(results, tasks))

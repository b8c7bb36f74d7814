"""An experiment config end to end: demonstrations, pretraining, evaluation, few-shot, tables.

    python -m experiments.pipeline --config cpu --out results/paper_cpu        # make paper-cpu
    python -m experiments.pipeline --config quick --out results/quickstart     # make quickstart
    python -m experiments.pipeline --config cpu --set seeds=0 --set train.max_steps=300 --out /tmp/try

1. expert demonstrations (the config's `train.demos` per task of its taskset,
   `fewshot.demos` per unseen task), in this process;
2. one job per (policy, seed), `workers` processes side by side: pretrain,
   evaluate closed loop on the pretraining tasks (`trials` paired trials),
   then fine-tune on each unseen task and evaluate it;
3. the tables (success mean ± SE over seeds, policy queries per successful
   episode, the same over paired trials), as `summary.md` and `summary.json`
   (`experiments.publish`).

Each run records its config's few-shot protocol and training settings in its
config.json (`experiment.RunRecord`), so that its row is named, and it is
adapted, as it was trained, whatever the config file says later: a job's
fine-tunes read their protocol from the run's record, as `skillplug fewshot`
does. The physics backend ("auto" too) is resolved once, when `run` starts.

Everything resumes: a run continues from its last checkpoint, an evaluation
already written (`<run>/eval/*.json`) is read back, not redone. SIGTERM or
SIGINT (Ctrl-C) stops every job cleanly, training jobs after checkpointing
their step (`in_workers`); the same command resumes. Each
ACT+SkillPlug evaluation also writes its routing weights, every query of
every trial, beside it (`*.routing.npz`, `protocol.write_routing`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import jax

import envs
from envs import toy_skills
from experiments import publish
from skillplug_jax import experiment, fewshot
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.startup import cpu_name
from skillplug_jax.evaluate import groups, toy_rollout, trials
from skillplug_jax.evaluate.routing import renamed
from skillplug_jax.evaluate.policy_controller import load_controller
from skillplug_jax.experiment import Experiment, FewShot, RunRecord, Variant
from skillplug_jax.train import loop, preemption, run_files
from skillplug_jax.train import toy as toy_train
from skillplug_jax.train.config import TrainConfig


def tasks_of(taskset: str) -> tuple[str, ...]:
  """A taskset name, a task name, or several of either, comma-separated (the toy's: envs/toy_skills.py)."""
  return tuple(n for part in taskset.split(",")
               for n in (toy_skills.TASKSETS.get(part) or envs.taskset(part)))


def pretrain_config(exp: Experiment, policy: str, seed: int, out: Path,
                    data_dir: Path | None = None) -> TrainConfig:
  """The run of (policy, seed) under `out`; datasets in `data_dir` (default out/datasets)."""
  cfg = exp.train_config(policy, seed)
  return dataclasses.replace(cfg, data_dir=str(data_dir or out / "datasets"),
                             workdir=str(out / "runs" / f"{cfg.taskset}_{policy}_{cfg.preset}_seed{seed}"))


def arms(exp: Experiment, out: Path) -> list[tuple[Variant, Experiment, Path]]:
  """(variant, its experiment, its output folder): OUT itself for a config without variants,
  OUT/<variant> for each variant (the datasets are shared, in OUT/datasets), and for a variant that
  adapts another's runs (`Variant.adapts`), that variant's folder."""
  return [(v, e, out / (v.adapts or v.name) if v.name else out) for v, e in experiment.expand(exp)]


def protocol_fields(plan: FewShot, policy: str) -> dict:
  """A few-shot result's protocol as training-key fields (`fewshot.trainable`, and the fine-tune's
  own overrides where it has any), so that two protocols on the same runs are two rows."""
  fields = {"fewshot.trainable": list(plan.trainable.of(policy))}
  if plan.train_overrides:
    fields["fewshot.train_overrides"] = list(plan.train_overrides)
  return fields


def evaluated(run: Path, tasks, exp: Experiment, name: str, source: Path, extra: dict | None = None) -> list[dict]:
  """The closed-loop results of `run` on `tasks`, read back when this evaluation was already written.

  source: the run whose training configuration and record the results are
  tabulated under (`run` itself, or a few-shot run's source: the table's rows
  are the pretrained runs).
  """
  path = run / "eval" / f"{name}_trials{exp.trials}_seed{exp.eval_seed}.json"
  if path.exists():  # written before today's key names too; where the run is now (a moved folder)
    return [dict(r, run=str(run), **({"routing_file": str(path.parent / Path(r["routing_file"]).name)}
                                      if r.get("routing_file") else {}))
            for r in renamed(json.loads(path.read_text()))["results"]]
  controller, cfg = load_controller(run)
  row = groups.row_fields(run_files.read_config(source), experiment.read_record(source))
  results = []
  for task in tasks:
    t0 = time.time()
    routing = (path.with_name(f"{path.stem}_{task.replace(':', '_')}.routing.npz") if cfg.model.is_skillplug else None)
    r = trials.evaluate_task(task, controller, cfg, exp.trials, exp.eval_seed, exp.eval_batch,
                             backend=exp.train.backend, routing_file=routing)
    r.update(run=str(run), **row, trained_on=cfg.backend, wall_s=round(time.time() - t0, 1),
             routing_file=str(routing) if routing else None, **(extra or {}))
    results.append(r)
  write_json_atomic(path, dict(results=results))
  return results


def job(exp: Experiment, policy: str, seed: int, out: Path, data_dir: Path | None = None,
        variant: str = "", record: RunRecord | None = None, adapts: str = "",
        protocol_in_rows: bool = False) -> dict:
  """Pretrain one (policy, seed), evaluate it, adapt it to every unseen task (one worker process).

  record: what the run records of its config (default `experiment.record(exp, policy)`, its
  preset read from the repository's configs), so that it is named and adapted later as now.
  The fine-tunes follow the few-shot protocol the run recorded (a resumed run: the one it
  started with), as `skillplug fewshot` does, not `exp.fewshot`. `exp.train.backend` is
  resolved (`run`): training and evaluation run on it.

  A config on the toy problem (`loop.is_toy`: taskset toy_skills) trains on demonstrations made
  in memory (`train.toy.train`, the same training step, a run directory like any other) and is
  evaluated by the toy's closed loop (`evaluate.toy_rollout.evaluated`, results in the same
  format); its extras per run (routing against the primitives, fixed-skill probe, zero-shot)
  come back under "toy".

  adapts: `variant` adapts the runs of this variant (`Variant.adapts`, in `out`, trained by an
  earlier job): its pretraining is read back, not tabulated again, and its fine-tunes follow
  `exp.fewshot` (its own protocol) into RUN_fewshot_<variant>/. protocol_in_rows: few-shot results
  carry their protocol in their training key (`protocol_fields`), so that protocols are rows.
  """
  envs.quiet_warp()
  label, stages = f"{variant + ' ' if variant else ''}{policy} seed {seed}", {}

  def stage(name: str, t0: float) -> None:
    stages[name] = round(time.time() - t0, 1)
    print(f"[pipeline] {label}: {name} done in {stages[name]:.0f} s", file=sys.stderr, flush=True)

  cfg = pretrain_config(exp, policy, seed, out, data_dir)
  toy = loop.is_toy(cfg)
  train, evaluate = (toy_train.train, toy_rollout.evaluated) if toy else (loop.train, evaluated)
  t0 = time.time()
  run = train(cfg, progress=False, record=record or experiment.record(exp, policy))
  stage("pretrain", t0)
  t0 = time.time()
  pretrain = evaluate(run, tasks_of(cfg.taskset), exp, cfg.taskset, run)
  extras = []
  if toy:
    extras = [dict(toy_rollout.run_extras(run, exp), run=str(run), variant=variant,
                   **groups.row_fields(run_files.read_config(run), experiment.read_record(run)))]
  stage("evaluate", t0)
  adapted = []
  if exp.run_fewshot:
    t0 = time.time()
    source, recorded = run_files.read_config(run), experiment.read_record(run)
    # the protocol the run recorded (this experiment's, its overrides included), or this arm's own
    plan = exp.fewshot if adapts else recorded.fewshot
    for unit, unit_tasks in fewshot.units(plan):  # each task, or each suite (`FewShot.per`)
      few = fewshot.fewshot_config(source, run, unit, plan, variant if adapts else "")
      few_run = train(few, progress=False, record=recorded)
      steps = few.num_steps(plan.demos * len(unit_tasks))  # the dataset holds `demos` episodes per task
      results = evaluate(few_run, unit_tasks, exp, unit, run, extra=dict(source=str(run)))
      adapted += [dict(r, trainable=list(few.trainable), steps=steps) for r in results]
    if protocol_in_rows:
      fields = protocol_fields(plan, policy)
      adapted = [dict(r, config={**r["config"], **fields}, overrides={**r["overrides"], **fields})
                 for r in adapted]
    stage("few-shot adapt + evaluate", t0)
  if adapts:  # its pretraining is its source's, tabulated there
    pretrain = []
  if variant:  # which arm of the experiment each result belongs to
    pretrain, adapted = [dict(r, variant=variant) for r in pretrain], [dict(r, variant=variant) for r in adapted]
  return dict(run=str(run), pretrain=pretrain, fewshot=adapted, stages_s=stages, **({"toy": extras} if toy else {}))


def in_workers(workers: int, args: list[tuple]) -> list[dict]:
  """`job(*a)` for each of `args` in `workers` processes side by side; their results in order.

  SIGTERM or SIGINT to this process (or Ctrl-C to the whole process group) stops every job cleanly:
  this process sets the pool's stop event and passes SIGTERM to its workers once (they ignore the
  signals themselves between jobs, so that none dies idle and breaks the pool); a training job
  checkpoints its step, an evaluation is dropped, a job not yet started does not start. Then
  `preemption.Stopped` is raised here, after every worker has stopped; the same command resumes.
  """
  ctx = multiprocessing.get_context("spawn")
  stop = ctx.Event()
  with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init, initargs=(stop,)) as pool:
    futures = {pool.submit(_worker_job, *a): i for i, a in enumerate(args)}
    with _PassSignals(stop) as signalled:
      done, stopped = {}, []
      for f in as_completed(futures):
        try:
          done[futures[f]] = f.result()
        except preemption.Stopped as e:
          stopped.append(e)
  if stopped or signalled.signum:
    for e in stopped:
      if isinstance(e, preemption.Preempted):
        print(f"[pipeline] {e}", file=sys.stderr, flush=True)
    raise preemption.Stopped(signalled.signum or stopped[0].signum)
  return [done[i] for i in range(len(args))]


class _PassSignals:
  """In the pipeline's process while its workers run: the first SIGTERM/SIGINT sets `stop` and passes
  SIGTERM to every worker; a second one acts at once (the default action)."""

  def __init__(self, stop):
    self.stop, self.signum, self._previous = stop, None, {}

  def _handle(self, signum, frame) -> None:
    self.signum = signum
    self.stop.set()  # before the signals: a worker that checks the event after them sees it
    for child in multiprocessing.active_children():
      os.kill(child.pid, signal.SIGTERM)
    print(f"[pipeline] {signal.Signals(signum).name}: stopping the jobs (training jobs checkpoint their "
          "step first) ...", file=sys.stderr, flush=True)
    self.__exit__()

  def __enter__(self) -> _PassSignals:
    self._previous = {s: signal.signal(s, self._handle) for s in preemption.SIGNALS}
    return self

  def __exit__(self, *exc) -> None:
    for s, previous in self._previous.items():
      signal.signal(s, previous if previous is not None else signal.SIG_DFL)
    self._previous = {}


_STOP = None  # in a worker process: the pool's stop event, set once by `_worker_init`


def _worker_init(stop) -> None:
  global _STOP
  _STOP = stop
  for s in preemption.SIGNALS:  # the pipeline's process coordinates: it passes SIGTERM to busy workers
    signal.signal(s, signal.SIG_IGN)


def _worker_job(*args) -> dict:
  """`job(*args)` in a worker: a SIGTERM raises `Stopped` (training checkpoints first); the stop
  event is read after the handler is in place, so that no job starts once a stop was asked for."""
  with preemption.RaiseOnSignal((signal.SIGTERM,)):
    if _STOP is not None and _STOP.is_set():
      raise preemption.Stopped(signal.SIGTERM)
    return job(*args)


def make_datasets(exp: Experiment, out: Path) -> float:
  """Every dataset the jobs read, generated here first (the workers then only read them)."""
  t0 = time.time()
  for _, arm, arm_out in arms(exp, out):
    if not arm.seeds or not arm.policies:
      continue
    source = pretrain_config(arm, arm.policies[0], arm.seeds[0], arm_out, out / "datasets")
    if loop.is_toy(source):  # the toy's demonstrations are made in memory by each job
      continue
    loop.load_data(source)
    if arm.run_fewshot:
      first_unseen = fewshot.units(arm.fewshot)[0][0]  # one dataset holds every unseen task
      loop.load_data(fewshot.fewshot_config(source, source.run_dir, first_unseen,
                                            dataclasses.replace(arm.fewshot, steps=1)))
  return round(time.time() - t0, 1)


def run(exp: Experiment, out: Path, configs: Path | None = None) -> dict:
  """Every job of `exp` (loaded from the directory `configs`, default the repository's) and the summary.
  The pipeline's edge: `exp.train.backend` ("auto" too) is resolved here, once, for every arm."""
  t_start = time.time()
  backend = envs.resolve_backend(exp.train.backend)
  exp = dataclasses.replace(exp, train=dataclasses.replace(exp.train, backend=backend))
  print(f"[pipeline] {exp.train.preset}: expert demonstrations ...", file=sys.stderr, flush=True)
  stages = {"demonstrations": make_datasets(exp, out)}
  # the slower policy first, so that the last job to start is a short one; arms that adapt another's
  # runs after every arm that trains (a run is trained by one process at a time)
  by_arm = arms(exp, out)
  protocol_in_rows = any(v.adapts for v, _, _ in by_arm)
  jobs = [(v, arm, arm_out, p, s) for adapting in (False, True) for v, arm, arm_out in by_arm
          if bool(v.adapts) == adapting for s in arm.seeds
          for p in sorted(arm.policies, key=lambda p: p != "skillplug")]
  print(f"[pipeline] {len(jobs)} jobs (variant, policy, seed) on {exp.workers} workers, physics on "
        f"{exp.train.backend} (a line per finished stage) ...", file=sys.stderr, flush=True)
  t0 = time.time()
  args = [(arm, p, s, arm_out, out / "datasets", v.name, experiment.record(arm, p, configs), v.adapts,
           protocol_in_rows) for v, arm, arm_out, p, s in jobs]
  phases = [[a for a in args if not a[7]], [a for a in args if a[7]]]
  parts = []
  for phase in phases:
    if not phase:
      continue
    if exp.workers == 1:  # in this process, one job after another
      with preemption.RaiseOnSignal():
        parts += [job(*a) for a in phase]
    else:
      parts += in_workers(exp.workers, phase)
  stages["jobs (parallel)"] = round(time.time() - t0, 1)
  jobs = [(v.name, arm, arm_out, p, s) for v, arm, arm_out, p, s in jobs]
  for (name, _, _, p, s), part in zip(jobs, parts):
    stages.update({f"{name + ' ' if name else ''}{p} seed {s} {k}": v for k, v in part["stages_s"].items()})
  ref = {stage: publish.reference_results(exp.reference, stage) if exp.reference else []
         for stage in ("pretrain", "fewshot")}
  # arms may train on different suites (libero_cpu): a row is evaluated on its own training taskset
  trained = [arm for _, arm, _ in by_arm if arm.seeds and arm.policies]
  pretrain_tasks = tuple(dict.fromkeys(t for arm in trained for t in tasks_of(arm.train.taskset)))
  fewshot_tasks = tuple(dict.fromkeys(t for arm in trained if arm.run_fewshot for t in tasks_of(arm.fewshot.taskset)))
  summary = dict(config=exp.train.preset, command=exp.command, experiment=dataclasses.asdict(exp),
                 pretrain=publish.merged_summary(parts, "pretrain", pretrain_tasks, ref["pretrain"],
                                                 row_tasks=lambda key: tasks_of(key["taskset"])),
                 stages_s=stages, wall_s=round(time.time() - t_start, 1), device=str(jax.devices()[0]),
                 backend=exp.train.backend, runs=[part["run"] for part in parts])
  if any(part["fewshot"] for part in parts):
    summary["fewshot"] = publish.merged_summary(parts, "fewshot", fewshot_tasks or tasks_of(exp.fewshot.taskset),
                                                ref["fewshot"])
  if exp.variants:
    summary["variants"] = publish.variant_rows(exp, summary)
  if any("toy" in part for part in parts):
    summary["toy"] = dict(publish.toy_summary(parts, summary),
                          mined_labels=toy_rollout.mined_label_agreement(exp.train))
    summary["cpu"] = cpu_name()
  return summary


def main(argv=None, default_config: str = "cpu", default_out: str = "") -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--config", default=default_config,
                 help=f"experiments/configs/NAME.py ({', '.join(experiment.names())}), or a path to a config file")
  p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                 help="override the experiment, e.g. --set seeds=0,1 --set trials=20 --set train.max_steps=500 "
                      "--set fewshot.steps=200 --set run_fewshot=false")
  p.add_argument("--out", default=default_out, help="datasets, runs and the summary go here (default results/<config>)")
  p.add_argument("--publish", default="", metavar="DIR",
                 help="also copy the summary and the routing arrays here (e.g. docs/results/paper_cpu)")
  p.add_argument("--variants", default="", metavar="A,B",
                 help="of a config with variants (an ablation, a sweep), run and tabulate only these")
  args = p.parse_args(argv)
  envs.quiet_warp()
  try:
    exp = experiment.get(args.config, args.set)
    exp = experiment.only(exp, args.variants, args.config)
    experiment.expand(exp)  # each variant's settings are checked before any work
    out = Path(args.out or f"results/{Path(args.config).stem}")
    summary = run(exp, out, experiment.directory(args.config))
  except preemption.Stopped as e:  # SIGTERM/SIGINT: finished stages and checkpoints are kept
    print(f"pipeline: {e}", file=sys.stderr)
    return e.exit_code
  except (ValueError, RuntimeError) as e:  # a worker's error arrives here; finished stages are kept
    print(f"pipeline: error: {e}", file=sys.stderr)
    return 2 if isinstance(e, ValueError) else 1
  text = publish.report(summary)
  print("\n" + text)
  write_json_atomic(out / "summary.json", summary)
  write_text_atomic(out / "summary.md", text + "\n")
  print(f"\nwrote {out / 'summary.md'} and summary.json")
  if args.publish:
    publish.publish(summary, text, Path(args.publish))
    print(f"published the summary and the routing arrays to {args.publish}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""The CPU quickstart: the whole SkillPlug pipeline, small, end to end.

    make quickstart      # or: python -m experiments.quickstart --out results/quickstart

1. expert demonstrations (state only, 10 per task) of the 7 `discoverse7`
   tasks and of the 4 unseen `discoverse_fewshot4` tasks, as RLDS datasets;
2. multi-task pretraining of ACT and ACT+SkillPlug at the `quick` preset;
3. closed-loop evaluation of both on the 7 pretraining tasks (paired trials);
4. few-shot adaptation of both to each unseen task, then its evaluation;
5. the tables (success rate, policy queries per successful episode, and the
   same over paired trials), printed and written beside the runs.

The physics runs on the `auto` backend (MuJoCo's C engine on a CPU). Stages
2-4 run as two processes, one per policy: the physics and the quick networks
keep about one core busy each, so the two cores of a laptop-class CPU finish
both in the time of the slower one.

Every stage reuses what an earlier (or killed) run left: finished datasets
and checkpoints are not redone. The numbers are a tiny-budget smoke result,
not the paper's protocol (see `make pretrain PRESET=paper`).
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import jax

import envs
from skillplug_jax import fewshot
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.evaluate import protocol, tables
from skillplug_jax.train import config, loop

PRETRAIN_TASKSET = "discoverse7"
FEWSHOT_TASKSET = "discoverse_fewshot4"
POLICIES = ("act", "skillplug")


def _pretrain_config(policy: str, out: Path, demos: int, seed: int) -> config.TrainConfig:
  return config.override(config.preset("quick", policy), [
      f"taskset={PRETRAIN_TASKSET}", f"demos={demos}", f"seed={seed}", f"data_dir={out / 'datasets'}",
      f"workdir={out / 'runs' / f'{PRETRAIN_TASKSET}_{policy}_quick_seed{seed}'}"])


def policy_pipeline(policy: str, out: Path, trials: int, demos: int, seed: int) -> dict:
  """Pretrain one policy, evaluate it, adapt it to the unseen task (one worker process)."""
  envs.quiet_warp()
  stages = {}

  def stage(name: str, t0: float) -> None:
    stages[name] = round(time.time() - t0, 1)
    print(f"[quickstart] {policy}: {name} done in {stages[name]:.0f} s", file=sys.stderr, flush=True)

  t0 = time.time()
  run = loop.train(_pretrain_config(policy, out, demos, seed), progress=False)
  stage("pretrain", t0)
  t0 = time.time()
  pretrain = protocol.evaluate_runs([run], envs.taskset(PRETRAIN_TASKSET), trials, batch=trials, progress=False)
  stage("evaluate", t0)
  t0 = time.time()
  adapted = fewshot.adapt_and_evaluate([run], FEWSHOT_TASKSET, demos, trials, batch=trials, progress=False)
  stage("few-shot adapt + evaluate", t0)
  return dict(run=str(run), pretrain=pretrain["results"], fewshot=adapted["results"], stages_s=stages)


def merged_summary(parts: list[dict], key: str, tasks) -> dict:
  """The workers' results of one stage and their tables: rows are grouped over both workers' runs."""
  results = [r for part in parts for r in part[key]]
  return dict(results=results, **tables.summarise(results, tasks))


def run(out: Path, trials: int, demos: int, seed: int) -> dict:
  t_start = time.time()
  # 1. every dataset first, in this process (the two workers then only read them)
  print("[quickstart] expert demonstrations (state only) ...", file=sys.stderr, flush=True)
  source = _pretrain_config("act", out, demos, seed)
  loop.load_data(source)
  first_unseen = envs.taskset(FEWSHOT_TASKSET)[0]  # the dataset holds every unseen task
  loop.load_data(fewshot.fewshot_config(source, source.run_dir, first_unseen, FEWSHOT_TASKSET, demos))
  stages = {"demonstrations": round(time.time() - t_start, 1)}
  # 2-4. one process per policy: physics and small networks use about one core each
  print(f"[quickstart] pretrain, evaluate and adapt {' and '.join(POLICIES)} in parallel, "
        f"physics on {envs.resolve_backend('auto')} "
        "(a line per finished stage) ...", file=sys.stderr, flush=True)
  t0 = time.time()
  with ProcessPoolExecutor(len(POLICIES), mp_context=multiprocessing.get_context("spawn")) as pool:
    jobs = [pool.submit(policy_pipeline, p, out, trials, demos, seed) for p in POLICIES]
    parts = [j.result() for j in jobs]
  stages["policies (parallel)"] = round(time.time() - t0, 1)
  for p, part in zip(POLICIES, parts):
    stages.update({f"{p} {k}": v for k, v in part["stages_s"].items()})

  return dict(pretrain=merged_summary(parts, "pretrain", envs.taskset(PRETRAIN_TASKSET)),
              fewshot=merged_summary(parts, "fewshot", envs.taskset(FEWSHOT_TASKSET)), stages_s=stages,
              wall_s=round(time.time() - t_start, 1), trials=trials, demos=demos, seed=seed,
              device=str(jax.devices()[0]), backend=envs.resolve_backend("auto"), pretrain_taskset=PRETRAIN_TASKSET,
              fewshot_taskset=FEWSHOT_TASKSET, runs=[part["run"] for part in parts])


def report(result: dict) -> str:
  t, d = result["trials"], result["demos"]
  lines = [
      "Multi-task:", "",
      tables.report(result["pretrain"], f"quick preset, {d} demos per task, {t} paired trials per task"), "",
      "Few-shot on the unseen tasks:", "",
      tables.report(result["fewshot"], f"{d} demos, {t} paired trials"), "",
      "Stages (s): " + ", ".join(f"{k} {v:.0f}" for k, v in result["stages_s"].items()),
      f"Runs: {', '.join(result['runs'])}",
      f"Wall time: {result['wall_s'] / 60:.1f} min on {result['device']} "
      "(a tiny-budget smoke run, not the paper's protocol)."]
  return "\n".join(lines)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", default="results/quickstart", help="datasets, runs and the summary go here")
  p.add_argument("--trials", type=int, default=10, help="paired evaluation episodes per task")
  p.add_argument("--demos", type=int, default=10, help="expert demonstrations per task")
  p.add_argument("--seed", type=int, default=0, help="training seed")
  args = p.parse_args(argv)
  if args.trials < 1 or args.demos < 1:
    p.error("--trials and --demos must be >= 1")
  envs.quiet_warp()
  out = Path(args.out)
  try:
    result = run(out, args.trials, args.demos, args.seed)
  except (ValueError, RuntimeError) as e:  # a worker's error arrives here; finished stages are kept
    print(f"quickstart: error: {e}", file=sys.stderr)
    return 2 if isinstance(e, ValueError) else 1
  text = report(result)
  print("\n" + text)
  write_json_atomic(out / "summary.json", result)
  write_text_atomic(out / "summary.md", text + "\n")
  print(f"\nwrote {out / 'summary.md'} and summary.json")
  return 0


if __name__ == "__main__":
  sys.exit(main())

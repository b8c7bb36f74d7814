"""ACT parity (issue 12): closed-loop success of our ACT under each departure from ACT.

    python -m experiments.act_parity --taskset quickstart3 --seeds 0,1,2
    python -m experiments.act_parity --taskset discoverse7 --variants before,input_std0.02_objnorm

Each variant is a set of config overrides on the `quick` preset's ACT. Every
(variant, seed) is trained, then evaluated on the same seeded trials of every
task (paired across variants and seeds); a finished run or evaluation is
reused, so a killed sweep resumes where it stopped. Two worker processes
(one per core) run (variant, seed) jobs side by side. The summary (success
mean and standard error over seeds, each seed's rate, mean control steps to
success) goes to OUT/summary_<taskset>_<n>seeds.{md,json}. `--policy skillplug`
runs the same variants on ACT+SkillPlug, whose encoder and action head are
ACT's (summary_<taskset>_skillplug_<n>seeds). With --reference
DIR (what `tools/ref_act_closed_loop.py` wrote: LeRobot's ACT on the same
batches and trials), the summary adds it as a row, and for each variant the
paired counts over the seeds both have: trials only the variant solved, and
trials only the reference solved.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import envs
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.evaluate.tables import mean_se
from skillplug_jax.model.config import LEGACY_DEFAULTS

# Every variant names each setting it depends on, so that a change of the
# defaults does not change what a finished run measured.
_AFTER = dict(positions="input", embed_init_std=0.02, normalize_object_state=True,
              pre_norm=True, cvae_zero_init=True)


def _overrides(grad_clip=None, **model) -> list[str]:
  out = [f"model.{k}={v}" for k, v in {**_AFTER, **model}.items()]
  return out + ([f"grad_clip={grad_clip}"] if grad_clip is not None else [])


# name -> (overrides of the quick ACT, what it tests).
VARIANTS = {
    "before": (_overrides(**LEGACY_DEFAULTS), "as before issue 12: positions added once to the contents, "
                                              "N(0, 1) tables, raw object state"),
    "input_std0.02": (_overrides(normalize_object_state=False),
                      "positions added once, N(0, 0.02) tables, raw object state"),
    "input_std0.02_objnorm": (_overrides(), "positions added once, N(0, 0.02) tables, "
                                            "object state normalised"),
    "qk_std1": (_overrides(positions="qk", embed_init_std=1.0, normalize_object_state=False),
                "ACT's wiring (positions on queries and keys, zero decoder contents), "
                "N(0, 1) tables as torch, raw object state"),
    "qk_std0.02": (_overrides(positions="qk", normalize_object_state=False),
                   "ACT's wiring, N(0, 0.02), raw object state"),
    "qk_std1_objnorm": (_overrides(positions="qk", embed_init_std=1.0),
                        "ACT's wiring, N(0, 1), object state normalised"),
    "qk_std0.02_objnorm": (_overrides(positions="qk"), "ACT's wiring, N(0, 0.02), object state normalised"),
    "post_norm": (_overrides(pre_norm=False), "input_std0.02_objnorm with ACT's post-norm layers"),
    "cvae_random_init": (_overrides(cvae_zero_init=False),
                         "input_std0.02_objnorm with a randomly initialised CVAE head (ACT's)"),
    "no_grad_clip": (_overrides(grad_clip=0), "input_std0.02_objnorm without gradient clipping (ACT clips none)"),
}


def run_dir(out: Path, taskset: str, variant: str, seed: int, policy: str = "act") -> Path:
  prefix = taskset if policy == "act" else f"{taskset}_{policy}"
  return out / "runs" / f"{prefix}_{variant}_seed{seed}"


def job(out: Path, taskset: str, variant: str, seed: int, trials: int, policy: str = "act") -> dict:
  """Train one (variant, seed) if not done, evaluate it if not done; its per-task results."""
  from skillplug_jax.evaluate import protocol
  from skillplug_jax.experiment import preset
  from skillplug_jax.train import config, loop
  envs.quiet_warp()
  run = run_dir(out, taskset, variant, seed, policy)
  result_file = run / f"eval_{trials}trials.json"
  if result_file.exists():
    return json.loads(result_file.read_text())
  cfg = config.override(preset("quick", policy), VARIANTS[variant][0] + [
      f"taskset={taskset}", f"seed={seed}", f"data_dir={out / 'datasets'}", f"workdir={run}"])
  t0 = time.time()
  loop.train(cfg, progress=False)
  train_s = time.time() - t0
  t0 = time.time()
  results = protocol.evaluate_runs([run], envs.taskset(taskset), trials, batch=trials, progress=False)["results"]
  keep = ("task", "abbr", "trials", "seed", "success_rate", "successes", "mean_steps_success",
          "mean_queries_success", "trial_success", "nan_episodes")
  out_ = dict(variant=variant, policy=policy, seed=seed, train_s=round(train_s, 1), eval_s=round(time.time() - t0, 1),
              tasks=[{k: r[k] for k in keep} for r in results])
  write_json_atomic(result_file, out_)
  print(f"[act_parity] {policy} {variant} seed {seed}: " + ", ".join(
      f"{r['abbr']} {100 * r['success_rate']:.0f}" for r in results), file=sys.stderr, flush=True)
  return out_


REFERENCE = "reference"  # the row name of LeRobot's ACT


def summarise(parts: list[dict], variants, tasks, reference: list[dict] = ()) -> dict:
  rows = {}
  ref = {r["seed"]: r for r in reference}
  for v in variants + ([REFERENCE] if reference else []):
    runs = sorted((p for p in parts if p["variant"] == v) if v != REFERENCE else reference,
                  key=lambda p: p["seed"])
    per_task = {}
    for i, task in enumerate(tasks):
      rates = [100 * r["tasks"][i]["success_rate"] for r in runs]
      steps = [r["tasks"][i]["mean_steps_success"] for r in runs if r["tasks"][i]["successes"]]
      per_task[task] = dict(
          mean=statistics.fmean(rates), se=_se(rates), seeds=rates,
          mean_steps_success=statistics.fmean(steps) if steps else None)
      if v != REFERENCE and ref:
        pairs = [(r["tasks"][i]["trial_success"], ref[r["seed"]]["tasks"][i]["trial_success"])
                 for r in runs if r["seed"] in ref]
        per_task[task]["paired_vs_reference"] = dict(
            seeds=len(pairs), only_this=sum(a and not b for x, y in pairs for a, b in zip(x, y)),
            only_reference=sum(b and not a for x, y in pairs for a, b in zip(x, y)))
    avgs = [statistics.fmean(100 * t["success_rate"] for t in r["tasks"]) for r in runs]
    what, overrides = (("LeRobot's ACT (tools/ref_act_closed_loop.py)", runs[0]["overrides"])
                       if v == REFERENCE else VARIANTS[v])
    rows[v] = dict(what=what, overrides=overrides, seeds=[r["seed"] for r in runs],
                   tasks=per_task, average=dict(mean=statistics.fmean(avgs), se=_se(avgs), seeds=avgs),
                   train_s=[r["train_s"] for r in runs])
  return rows


def _se(x):
  """The SE of `tables.mean_se`, 0 for one seed (this table prints one for every cell)."""
  return mean_se(x)[1] or 0.0


def markdown(rows: dict, tasks) -> str:
  abbr = [envs.task_class(t).abbr for t in tasks]
  head = "| variant | " + " | ".join(abbr) + " | Avg. |"
  lines = [head, "|" + "---|" * (len(tasks) + 2)]
  for v, r in rows.items():
    cells = []
    for t in tasks:
      c = r["tasks"][t]
      steps = f" ({c['mean_steps_success']:.0f})" if c["mean_steps_success"] is not None else ""
      cells.append(f"{c['mean']:.1f} ± {c['se']:.1f}{steps}")
    lines.append(f"| {v} | " + " | ".join(cells) + f" | {r['average']['mean']:.1f} ± {r['average']['se']:.1f} |")
  paired = [(v, r) for v, r in rows.items() if "paired_vs_reference" in r["tasks"][tasks[0]]]
  if paired:
    lines += ["", "Paired with the reference, trial by trial over the seeds both have "
              "(solved by this variant only / by the reference only):", "",
              "| variant | " + " | ".join(abbr) + " |", "|" + "---|" * (len(tasks) + 1)]
    for v, r in paired:
      cells = [r["tasks"][t]["paired_vs_reference"] for t in tasks]
      lines.append(f"| {v} | " + " | ".join(f"{c['only_this']} / {c['only_reference']}" for c in cells) + " |")
  lines += ["", "Per seed (success %, tasks in order):", ""]
  for v, r in rows.items():
    lines.append(f"- {v} ({r['what']}): " + "; ".join(
        f"seed {s}: " + "/".join(f"{r['tasks'][t]['seeds'][i]:.0f}" for t in tasks)
        for i, s in enumerate(r["seeds"])))
  return "\n".join(lines)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--taskset", default="quickstart3")
  p.add_argument("--policy", default="act", choices=("act", "skillplug"),
                 help="whose departures: ACT's, or ACT+SkillPlug's (same encoder and action head)")
  p.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of: {', '.join(VARIANTS)}")
  p.add_argument("--seeds", default="0,1,2", help="training seeds")
  p.add_argument("--trials", type=int, default=50, help="paired evaluation episodes per task")
  p.add_argument("--workers", type=int, default=2, help="jobs side by side (one per core)")
  p.add_argument("--out", default="results/act_parity")
  p.add_argument("--reference", default="", metavar="DIR",
                 help="tools/ref_act_closed_loop.py's output directory, to add as a row and pair with")
  args = p.parse_args(argv)
  variants = [v for v in args.variants.split(",") if v]
  unknown = [v for v in variants if v not in VARIANTS]
  if unknown:
    p.error(f"unknown variant(s) {unknown}; valid: {', '.join(VARIANTS)}")
  seeds = [int(s) for s in args.seeds.split(",") if s]
  tasks = envs.taskset(args.taskset)
  out = Path(args.out)
  from skillplug_jax.experiment import preset
  from skillplug_jax.train import config, loop
  # The dataset first, in this process, so that the workers only read it.
  loop.load_data(config.override(preset("quick", "act"), [
      f"taskset={args.taskset}", f"data_dir={out / 'datasets'}"]), progress=True)
  t0 = time.time()
  todo = [(v, s) for v in variants for s in seeds]
  with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
    parts = list(pool.map(job, *zip(*[(out, args.taskset, v, s, args.trials, args.policy)
                                      for v, s in todo])))
  reference = []
  if args.reference:
    files = [Path(args.reference) / f"{args.taskset}_seed{s}.json" for s in seeds]
    reference = [json.loads(f.read_text()) for f in files if f.exists()]
    if not reference:
      p.error(f"--reference {args.reference}: none of {', '.join(f.name for f in files)} is there")
  rows = summarise(parts, variants, tasks, reference)
  text = markdown(rows, tasks)
  print(text)
  name = f"summary_{args.taskset}{'' if args.policy == 'act' else '_' + args.policy}_{len(seeds)}seeds"
  # Runs are reused, so this invocation's wall time says little; each job's
  # own train and eval seconds (summed here) are what the runs cost.
  write_json_atomic(out / f"{name}.json", dict(
      taskset=args.taskset, trials=args.trials, seeds=seeds, policy=args.policy,
      invocation_wall_s=round(time.time() - t0, 1),
      jobs_train_eval_s=round(sum(p["train_s"] + p["eval_s"] for p in parts), 1), rows=rows))
  write_text_atomic(out / f"{name}.md", text + "\n")
  print(f"wrote {out / name}.md and .json")
  return 0


if __name__ == "__main__":
  sys.exit(main())

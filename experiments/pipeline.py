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
   episode, the same over paired trials), as `summary.md` and `summary.json`.

Everything resumes: a run continues from its last checkpoint, an evaluation
already written (`<run>/eval/*.json`) is read back, not redone. Each
ACT+SkillPlug evaluation also writes its routing weights, every query of
every trial, beside it (`*.routing.npz`, `protocol.write_routing`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import jax

import envs
from experiments import configs
from skillplug_jax import fewshot
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.evaluate import groups, protocol, tables
from skillplug_jax.evaluate.policy_controller import load_controller
from skillplug_jax.train import checkpoint, loop
from skillplug_jax.train.config import TrainConfig


def tasks_of(taskset: str) -> tuple[str, ...]:
  """A taskset name, a task name, or several of either, comma-separated."""
  return tuple(n for part in taskset.split(",") for n in envs.taskset(part))


def pretrain_config(exp: configs.Experiment, policy: str, seed: int, out: Path,
                    data_dir: Path | None = None) -> TrainConfig:
  """The run of (policy, seed) under `out`; datasets in `data_dir` (default out/datasets)."""
  cfg = exp.train_config(policy, seed)
  return dataclasses.replace(cfg, data_dir=str(data_dir or out / "datasets"),
                             workdir=str(out / "runs" / f"{cfg.taskset}_{policy}_{cfg.preset}_seed{seed}"))


def arms(exp: configs.Experiment, out: Path) -> list[tuple[configs.Variant, configs.Experiment, Path]]:
  """(variant, its experiment, its output folder): OUT itself for a config without variants,
  OUT/<variant> for each variant (the datasets are shared, in OUT/datasets)."""
  return [(v, e, out / v.name if v.name else out) for v, e in configs.expand(exp)]


def evaluated(run: Path, tasks, exp: configs.Experiment, name: str, train_cfg: TrainConfig,
              extra: dict | None = None) -> list[dict]:
  """The closed-loop results of `run` on `tasks`, read back when this evaluation was already written.

  train_cfg: the training configuration the results are tabulated under (a
  few-shot run's is its source's: the table's rows are the pretrained runs).
  """
  path = run / "eval" / f"{name}_trials{exp.trials}_seed{exp.eval_seed}.json"
  if path.exists():
    return json.loads(path.read_text())["results"]
  controller, cfg = load_controller(run)
  results = []
  for task in tasks:
    t0 = time.time()
    routing = (path.with_name(f"{path.stem}_{task}.routing.npz") if cfg.model.is_skillplug else None)
    r = protocol.evaluate_task(task, controller, exp.trials, exp.eval_seed, exp.eval_batch,
                               render=cfg.model.use_images, image_size=cfg.model.image_size,
                               routing_file=routing)
    r.update(run=str(run), policy=groups.policy_label(train_cfg), train_seed=train_cfg.seed,
             preset=train_cfg.preset, config=groups.training_key(train_cfg), trained_on=cfg.backend,
             wall_s=round(time.time() - t0, 1), routing_file=str(routing) if routing else None,
             **(extra or {}))
    results.append(r)
  write_json_atomic(path, dict(results=results))
  return results


def job(exp: configs.Experiment, policy: str, seed: int, out: Path, data_dir: Path | None = None,
        variant: str = "") -> dict:
  """Pretrain one (policy, seed), evaluate it, adapt it to every unseen task (one worker process)."""
  envs.quiet_warp()
  label, stages = f"{variant + ' ' if variant else ''}{policy} seed {seed}", {}

  def stage(name: str, t0: float) -> None:
    stages[name] = round(time.time() - t0, 1)
    print(f"[pipeline] {label}: {name} done in {stages[name]:.0f} s", file=sys.stderr, flush=True)

  cfg = pretrain_config(exp, policy, seed, out, data_dir)
  t0 = time.time()
  run = loop.train(cfg, progress=False)
  stage("pretrain", t0)
  t0 = time.time()
  pretrain = evaluated(run, tasks_of(cfg.taskset), exp, cfg.taskset, checkpoint.read_config(run))
  stage("evaluate", t0)
  adapted = []
  if exp.run_fewshot:
    t0 = time.time()
    source = checkpoint.read_config(run)
    for task in tasks_of(exp.fewshot.taskset):
      few = fewshot.fewshot_config(source, run, task, exp.fewshot.taskset, exp.fewshot.demos,
                                   steps=exp.fewshot.steps, trainable=exp.fewshot.trainable(policy))
      few_run = loop.train(few, progress=False)
      steps = few.num_steps(exp.fewshot.demos)  # the dataset holds `demos` episodes of the task
      results = evaluated(few_run, [task], exp, task, source, extra=dict(source=str(run)))
      adapted += [dict(r, trainable=list(few.trainable), steps=steps) for r in results]
    stage("few-shot adapt + evaluate", t0)
  if variant:  # which arm of the experiment each result belongs to
    pretrain, adapted = [dict(r, variant=variant) for r in pretrain], [dict(r, variant=variant) for r in adapted]
  return dict(run=str(run), pretrain=pretrain, fewshot=adapted, stages_s=stages)


def merged_summary(parts: list[dict], key: str, tasks, reference: list[dict] = ()) -> dict:
  """The jobs' results of one stage (and the reference's) and their tables: rows group every job's runs."""
  results = list(reference) + [r for part in parts for r in part[key]]
  return dict(results=results, **tables.summarise(results, tasks))


def make_datasets(exp: configs.Experiment, out: Path) -> float:
  """Every dataset the jobs read, generated here first (the workers then only read them)."""
  t0 = time.time()
  for _, arm, arm_out in arms(exp, out):
    if not arm.seeds or not arm.policies:
      continue
    source = pretrain_config(arm, arm.policies[0], arm.seeds[0], arm_out, out / "datasets")
    loop.load_data(source)
    if arm.run_fewshot:
      first_unseen = tasks_of(arm.fewshot.taskset)[0]  # one dataset holds every unseen task
      loop.load_data(fewshot.fewshot_config(source, source.run_dir, first_unseen, arm.fewshot.taskset,
                                            arm.fewshot.demos, steps=1, trainable=()))
  return round(time.time() - t0, 1)


def reference_results(path: str, stage: str) -> list[dict]:
  """The results of one stage of a published summary, marked as read from it."""
  p = Path(path)
  if not p.exists():
    raise ValueError(f"reference summary {p} does not exist (a published pipeline summary.json)")
  summary = json.loads(p.read_text())
  return [dict(r, reference=str(p), config=groups.normalised(r["config"]))
          for r in summary.get(stage, {}).get("results", [])]


def run(exp: configs.Experiment, out: Path) -> dict:
  t_start = time.time()
  print(f"[pipeline] {exp.train.preset}: expert demonstrations ...", file=sys.stderr, flush=True)
  stages = {"demonstrations": make_datasets(exp, out)}
  # the slower policy first, so that the last job to start is a short one
  jobs = [(v.name, arm, arm_out, p, s) for v, arm, arm_out in arms(exp, out) for s in arm.seeds
          for p in sorted(arm.policies, key=lambda p: p != "skillplug")]
  print(f"[pipeline] {len(jobs)} jobs (variant, policy, seed) on {exp.workers} workers, physics on "
        f"{envs.resolve_backend(exp.train.backend)} (a line per finished stage) ...", file=sys.stderr, flush=True)
  t0 = time.time()
  args = [(arm, p, s, arm_out, out / "datasets", name) for name, arm, arm_out, p, s in jobs]
  if exp.workers == 1:  # in this process, one job after another
    parts = [job(*a) for a in args]
  else:
    with ProcessPoolExecutor(exp.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
      futures = {pool.submit(job, *a): i for i, a in enumerate(args)}
      done = {futures[f]: f.result() for f in as_completed(futures)}
    parts = [done[i] for i in range(len(jobs))]
  stages["jobs (parallel)"] = round(time.time() - t0, 1)
  for (name, _, _, p, s), part in zip(jobs, parts):
    stages.update({f"{name + ' ' if name else ''}{p} seed {s} {k}": v for k, v in part["stages_s"].items()})
  ref = {stage: reference_results(exp.reference, stage) if exp.reference else [] for stage in ("pretrain", "fewshot")}
  summary = dict(config=exp.train.preset, command=exp.command, experiment=dataclasses.asdict(exp),
                 pretrain=merged_summary(parts, "pretrain", tasks_of(exp.train.taskset), ref["pretrain"]),
                 stages_s=stages, wall_s=round(time.time() - t_start, 1), device=str(jax.devices()[0]),
                 backend=envs.resolve_backend(exp.train.backend), runs=[part["run"] for part in parts])
  if any(part["fewshot"] for part in parts):
    summary["fewshot"] = merged_summary(parts, "fewshot", tasks_of(exp.fewshot.taskset), ref["fewshot"])
  if exp.variants:
    summary["variants"] = variant_rows(exp, summary)
  return summary


def variant_rows(exp: configs.Experiment, summary: dict) -> list[dict]:
  """Each variant (and each reference row): its label, overrides, and its row's name in each
  stage's tables (names depend on the rows beside it, so a stage's may differ from another's)."""
  stages = [s for s in ("pretrain", "fewshot") if s in summary]

  def row_of(stage, match):
    return next((name for r in summary[stage]["results"] if match(r)
                 for name, row in summary[stage]["rows"].items() if row["config"] == r["config"]), None)

  out = [dict(variant=v.name, label=v.label or v.name, overrides=list(v.overrides),
              rows={s: row_of(s, lambda r, v=v: r.get("variant") == v.name) for s in stages},
              routing_entropy_frac=routing_entropy([r for r in summary["pretrain"]["results"]
                                                    if r.get("variant") == v.name]))
         for v in exp.variants]
  if exp.reference:
    for name, row in summary["pretrain"]["rows"].items():
      mine = [r for r in summary["pretrain"]["results"] if r.get("reference") and r["config"] == row["config"]]
      if not mine:
        continue
      out.append(dict(variant="", label=f"{name} (reference)", overrides=[],
                      rows={s: row_of(s, lambda r, c=row["config"]: bool(r.get("reference")) and r["config"] == c)
                            for s in stages},
                      routing_entropy_frac=routing_entropy(mine)))
  return out


def routing_file(r: dict) -> Path | None:
  """Where a result's routing array is: beside its run, or (a reference's) where it was published."""
  if r.get("routing_file") and Path(r["routing_file"]).exists():
    return Path(r["routing_file"])
  if r.get("reference"):
    published = Path(r["reference"]).parent / "routing" / (
        f"{r['config']['model.policy']}_seed{r['train_seed']}_pretrain_{r['task']}.npz")
    return published if published.exists() else None
  return None


def routing_entropy(results: list[dict]) -> float | None:
  """Mean per-query routing entropy as a fraction of log K over these (pretraining) results
  (1: uniform routing at every query); None without routing arrays (ACT)."""
  from skillplug_jax.evaluate import routing
  files = [f for f in map(routing_file, results) if f is not None]
  if not files:
    return None
  return float(sum(s["entropy_frac"] for s in routing.summarise_files(files)) / len(files))


def publish(summary: dict, text: str, dest: Path) -> None:
  """The summary and every routing array, in one folder that can be committed and read by the notebooks.

  dest/summary.{md,json}; dest/routing/[<variant>_]<policy>_seed<S>_<stage>_<task>.npz
  (stage: pretrain or fewshot) and dest/routing/index.json, a list of
  {policy, seed, stage, task, file, success_rate, config, variant}.
  """
  import shutil
  dest = Path(dest)
  (dest / "routing").mkdir(parents=True, exist_ok=True)
  index = []
  for stage in ("pretrain", "fewshot"):
    for r in summary.get(stage, {}).get("results", []):
      if not r.get("routing_file") or r.get("reference"):  # a reference's arrays are where it was published
        continue
      arm = f"{r['variant']}_" if r.get("variant") else ""
      name = f"{arm}{r['config']['model.policy']}_seed{r['train_seed']}_{stage}_{r['task']}.npz"
      tmp = dest / "routing" / (name + ".tmp")
      shutil.copyfile(r["routing_file"], tmp)
      tmp.replace(dest / "routing" / name)
      index.append(dict(policy=r["policy"], seed=r["train_seed"], stage=stage, task=r["task"], file=name,
                        success_rate=r["success_rate"], config=groups.key_id(r["config"]),
                        variant=r.get("variant", "")))
  write_json_atomic(dest / "routing" / "index.json", index)
  write_json_atomic(dest / "summary.json", summary)
  write_text_atomic(dest / "summary.md", text + "\n")


def comparison(table: dict, stage: str) -> str:
  """ACT+SkillPlug minus ACT on each task and on Avg., with the standard error of the difference
  (the seeds of the two rows are independent runs: SE = sqrt(SE_a^2 + SE_b^2))."""
  rows = table["rows"]
  if "ACT" not in rows or "ACT+SkillPlug" not in rows:
    return ""
  parts = []
  for key, name in zip(table["tasks"] + ["Avg."], table["abbr"] + ["Avg."]):
    a, b = rows["ACT+SkillPlug"]["cells"][key], rows["ACT"]["cells"][key]
    if a is None or b is None:
      continue
    diff = a[0] - b[0]
    if a[1] is None or b[1] is None:
      parts.append(f"{name} {diff:+.1f}")
      continue
    se = (a[1] ** 2 + b[1] ** 2) ** 0.5
    parts.append(f"{name} {diff:+.1f} ± {se:.1f}" + (f" ({diff / se:+.1f} SE)" if se > 0 else ""))
  return f"ACT+SkillPlug minus ACT, {stage}: " + ", ".join(parts)


def _fewshot_steps(summary: dict) -> str:
  steps = sorted({r["steps"] for r in summary["fewshot"]["results"] if r.get("steps") is not None})
  return "/".join(map(str, steps)) or str(summary["experiment"]["fewshot"]["steps"])


def _avg(table: dict, row: str) -> str:
  cell = table["rows"].get(row, {}).get("cells", {}).get("Avg.")
  return "-" if cell is None else (f"{cell[0]:.1f}" if cell[1] is None else f"{cell[0]:.1f} ± {cell[1]:.1f}")


def per_seed_avg(summary: dict, stage: str, row: str) -> dict[int, float]:
  """{training seed: its success rate (%) averaged over the stage's tasks} of one row."""
  cfg = summary[stage]["rows"][row]["config"]
  rates = {}
  for r in summary[stage]["results"]:
    if r["config"] == cfg:
      rates.setdefault(r["train_seed"], []).append(100 * r["success_rate"])
  return {s: sum(v) / len(v) for s, v in sorted(rates.items())}


def variants_report(summary: dict) -> str:
  """One line per arm: its Avg. success in each stage, and each seed's, so that single-seed arms can
  be read against the same seed of the others."""
  stages = [s for s in ("pretrain", "fewshot") if s in summary]
  head = (["variant", "row", "seeds"] + [f"{'Multi-task' if s == 'pretrain' else 'Few-shot'} Avg. (per seed)"
                                          for s in stages] + ["routing entropy / log K"])
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for v in summary["variants"]:
    cells = []
    for s in stages:
      row = v["rows"].get(s)
      if row is None:
        cells.append("-")
        continue
      seeds = per_seed_avg(summary, s, row)
      cells.append(f"{_avg(summary[s]['table'], row)} ({', '.join(f's{k}: {x:.1f}' for k, x in seeds.items())})")
    row = v["rows"]["pretrain"]
    seeds = summary["pretrain"]["rows"][row]["seeds"] if row else []
    ent = v.get("routing_entropy_frac")
    cells.append("-" if ent is None else f"{ent:.3f}")
    lines.append(f"| {v['label']} | {row or '-'} | {','.join(map(str, seeds))} | " + " | ".join(cells) + " |")
  return "\n".join(lines)


def report(summary: dict) -> str:
  exp = summary["experiment"]
  t, d, seeds = exp["trials"], exp["train"]["demos"], exp["seeds"]
  seeds_text = ("training seeds per row as listed under Variants" if summary.get("variants")
                else f"{len(seeds)} training seed(s)")
  lines = []
  if summary.get("variants"):
    lines += ["Variants:", "", variants_report(summary), ""]
  lines += ["Multi-task:", "",
            tables.report(summary["pretrain"], f"`{summary['config']}` config, {d} demos per task, "
                          f"{seeds_text}, {t} paired trials per task"), "",
            comparison(summary["pretrain"]["table"], "success points, multi-task"), ""]
  if "fewshot" in summary:
    fs = exp["fewshot"]
    lines += ["Few-shot on the unseen tasks:", "",
              tables.report(summary["fewshot"], f"{fs['demos']} demos, {_fewshot_steps(summary)} fine-tuning "
                            f"steps, {t} paired trials"), "",
              comparison(summary["fewshot"]["table"], "success points, few-shot"), ""]
  lines += ["Stages (s): " + ", ".join(f"{k} {v:.0f}" for k, v in summary["stages_s"].items()),
            f"Runs: {', '.join(summary['runs'])}",
            f"Wall time: {summary['wall_s'] / 60:.1f} min on {summary['device']}, physics on {summary['backend']}."]
  return "\n".join(lines)


def main(argv=None, default_config: str = "cpu", default_out: str = "") -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--config", default=default_config, help=f"experiments/configs/NAME.py ({', '.join(configs.names())})")
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
    exp = configs.get(args.config, args.set)
    exp = configs.only(exp, args.variants, args.config)
    if any(not arm.seeds or not arm.policies for _, arm in configs.expand(exp)) or exp.trials < 1 or exp.workers < 1:
      raise ValueError("seeds and policies must be non-empty, trials and workers >= 1")
    out = Path(args.out or f"results/{args.config}")
    summary = run(exp, out)
  except (ValueError, RuntimeError) as e:  # a worker's error arrives here; finished stages are kept
    print(f"pipeline: error: {e}", file=sys.stderr)
    return 2 if isinstance(e, ValueError) else 1
  text = report(summary)
  print("\n" + text)
  write_json_atomic(out / "summary.json", summary)
  write_text_atomic(out / "summary.md", text + "\n")
  print(f"\nwrote {out / 'summary.md'} and summary.json")
  if args.publish:
    publish(summary, text, Path(args.publish))
    print(f"published the summary and the routing arrays to {args.publish}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

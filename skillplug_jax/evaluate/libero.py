"""The evaluation protocol on LIBERO: the benchmark's paired trials, per-task and per-suite tables.

Trial i of a task starts from the benchmark's init state i for every policy, as LIBERO's own
evaluation and the field's do (50 per task), so two policies are compared on the same starts
(`envs.libero.rollout`). Each trial has two outcomes: LIBERO's success (its predicate at some
step within the suite's limit: what published LIBERO numbers count) and ours (placed and
released, held 0.5 s). Tables are the project's (`tables.success_table`: a row per policy, a
column per task, `Avg.` over tasks computed per training seed) and the paper's LIBERO layout: a
column per suite (Spatial, Object, Goal, Long) and their average.

A policy is an `envs.rollout.Controller` reading our LIBERO layout (`envs.libero.layout`), one per
training seed; the seeds' results are aggregated as mean +- SE.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from tqdm import tqdm

from envs.libero import rollout, suites
from envs.rollout import Controller
from skillplug_jax.evaluate import protocol, tables

MEASURES = ("libero_success", "success")  # LIBERO's rule, ours
# How far the trials got: the share of the goal's atoms held at some step within the limit (each on
# its own), over atoms and trials. Results from before it was recorded lack it, and a summary of
# them leaves its table out (`experiments.publish.libero_tables`).
PROGRESS = "atoms_reached"
# The paper's LIBERO table (tab:libero_oft_mt: OpenVLA-OFT, K = 8, 3 seeds, 50 trials per task, mean
# and SE %), by stage: multi-task per suite; few-shot after pretraining on Long, 5 demos per task.
# Its backbone is a 7B vision-language-action model trained on LIBERO's human demonstrations, with
# images; ours is a small ACT on our scripted demonstrations: these rows stand beside ours, they are
# not the same experiment.
PAPER = {
    "pretrain": {"OpenVLA-OFT": {"Long": (92.9, 1.2), "Object": (97.6, 0.6), "Goal": (96.5, 0.9), "Spatial": (96.4, 0.8)},
                 "OpenVLA-OFT+SkillPlug": {"Long": (93.5, 1.1), "Object": (97.8, 0.7), "Goal": (96.7, 0.9),
                                           "Spatial": (95.6, 0.7)}},
    "fewshot": {"OpenVLA-OFT": {"Object": (47.4, 2.1), "Goal": (45.4, 2.2), "Spatial": (42.0, 2.4)},
                "OpenVLA-OFT+SkillPlug": {"Object": (79.6, 1.6), "Goal": (83.2, 1.7), "Spatial": (86.8, 2.0)}},
}


def evaluate_task(name: str, controller: Controller, trials: int = suites.INIT_STATES_PER_TASK, videos: int = 0,
                  video_dir: str | Path | None = None, routing_file: str | Path | None = None) -> dict:
  """Both success rates of one controller on one LIBERO task, and every trial's outcomes (paired
  by init state). `success_rate` is ours (placed and released, held 0.5 s: what the project's
  tables count), `libero_success_rate` LIBERO's. videos > 0 writes the agentview camera of the
  first trials to `video_dir/<suite>_<index>_trialNN.gif`. routing_file: every query's routing
  weights (ACT+SkillPlug), as `protocol.write_routing` writes DISCOVERSE's."""
  if videos and video_dir is None:
    raise ValueError("videos need a video_dir")
  r = rollout.run_trials(name, controller, trials, frames=videos)
  if videos:
    protocol.write_videos(r.frames, Path(video_dir), name.replace(":", "_"))
  task = suites.parse(name)
  reached = r.first_success_step[r.libero_success]
  routing = [r.routing] if r.routing is not None else []
  if routing_file is not None and routing:
    protocol.write_routing(routing_file, name, routing, trials, r.success, r.first_success_step, r.queries)
  success = r.success
  return dict(task=name, abbr=suites.abbr(name), name=task.name, language=task.language, trials=trials,
              success_rate=float(success.mean()), successes=int(success.sum()),
              libero_success_rate=float(r.libero_success.mean()),
              trial_success=success.tolist(), trial_libero_success=r.libero_success.tolist(),
              goal_atoms=list(r.atoms),
              atoms_reached_rate=float(r.atoms_reached.mean()), trial_atoms_reached=r.atoms_reached.tolist(),
              trial_queries=r.queries.tolist(), trial_success_step=r.declared_step.tolist(),
              mean_queries_success=float(r.queries[success].mean()) if success.any() else None,
              mean_steps_success=float(r.declared_step[success].mean()) if success.any() else None,
              median_steps=float(np.median(reached)) if reached.size else None, time_limit=task.time_limit,
              mean_weights=(np.nanmean(r.routing.reshape(-1, r.routing.shape[-1]), axis=0).tolist()
                            if routing and np.isfinite(r.routing).any() else None),
              **({"diagnostics": protocol.routing_diagnostics(routing, trials)} if routing else {}))


def evaluate(policies: Mapping[str, Sequence[Controller]], tasks: Sequence[str],
             trials: int = suites.INIT_STATES_PER_TASK, progress: bool = True) -> dict:
  """Every policy (its controllers: one per training seed) on every task; the results and tables."""
  results = []
  jobs = [(p, s, t) for p, seeds in policies.items() for s in range(len(seeds)) for t in tasks]
  for policy, seed, task in tqdm(jobs, desc="LIBERO trials", unit="task", file=sys.stderr, disable=not progress):
    results.append({"policy": policy, "seed": seed, **evaluate_task(task, policies[policy][seed], trials)})
  return {"results": results, "tables": {m: tables_of(results, tasks, m) for m in MEASURES + (PROGRESS,)}}


def evaluate_runs(run_dirs: Sequence[str | Path], tasks: Sequence[str], trials: int = suites.INIT_STATES_PER_TASK,
                  videos: int = 0, video_dir: str | Path = "videos", progress: bool = True) -> dict:
  """Trained runs (`skillplug pretrain` on a LIBERO taskset) on LIBERO tasks. Runs whose training
  configurations differ only in the seed are one row's seeds (`groups`, as `protocol.evaluate_runs`)."""
  from skillplug_jax import experiment
  from skillplug_jax.evaluate import groups
  from skillplug_jax.evaluate.policy_controller import load_controller
  loaded = [(run, *load_controller(run)) for run in run_dirs]  # every checkpoint first: fail before any trial
  fields = {run: groups.row_fields(cfg, experiment.read_record(run)) for run, _, cfg in loaded}
  rows = groups.group_rows(list(fields.values()))
  name_of = {groups.key_id(row["config"]): name for name, row in rows.items()}
  results = []
  jobs = [(run, c, cfg, t) for run, c, cfg in loaded for t in tasks]
  for run, controller, cfg, task in tqdm(jobs, desc="LIBERO trials", unit="task", file=sys.stderr,
                                         disable=not progress):
    r = evaluate_task(task, controller, trials, videos, Path(video_dir) / Path(run).name)
    row = fields[run]
    results.append({"policy": name_of[groups.key_id(row["config"])], "seed": row["train_seed"], "run": str(run), **r})
  return {"trials": trials, "results": results, "rows": rows,
          "tables": {m: tables_of(results, tasks, m) for m in MEASURES + (PROGRESS,)}}


def report(out: dict) -> str:
  """The per-suite tables of both rules and the per-task table of LIBERO's, as markdown."""
  lines = []
  for measure, title in (("libero_success", "LIBERO's success (its predicate at any step within the limit)"),
                         ("success", "our success (placed, released, held 0.5 s)")):
    t = out["tables"][measure]
    lines += [f"**{title}**, {out['trials']} paired trials per task (the benchmark's init states), %:", "",
              markdown(t["per_suite"]), ""]
    if measure == "libero_success":
      per_task = t["per_task"]
      cols = per_task["abbr"] + ["Avg."]
      lines += ["| policy | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
      for policy, row in per_task["rows"].items():
        cells = [row["cells"][c] for c in per_task["tasks"]] + [row["cells"]["Avg."]]
        lines.append(f"| {policy} | " + " | ".join("-" if c is None else f"{c[0]:.0f}" if c[1] is None
                                                   else f"{c[0]:.0f} ± {c[1]:.0f}" for c in cells) + " |")
      lines.append("")
  if PROGRESS in out["tables"]:
    lines += ["**How far the trials got**: the goal's atoms that held at some step within the limit, each on "
              "its own, % of atoms and trials:", "", markdown(out["tables"][PROGRESS]["per_suite"]), ""]
  return "\n".join(lines)


def tables_of(results: Sequence[dict], tasks: Sequence[str], measure: str = "libero_success") -> dict:
  """The per-task table and the paper's per-suite table of `measure` ("libero_success",
  "success", or `PROGRESS`: the share of goal atoms reached), from `evaluate`'s results."""
  if measure not in MEASURES + (PROGRESS,):
    raise ValueError(f"unknown measure {measure!r}; measures: {', '.join(MEASURES + (PROGRESS,))}")
  key = f"{measure}_rate"
  rates: dict = {}
  for r in results:
    rates.setdefault(r["policy"], {}).setdefault(r["task"], {})[r["seed"]] = r[key]
  per_task = {p: {t: [by_seed[s] for s in sorted(by_seed)] for t, by_seed in row.items()} for p, row in rates.items()}
  return {"per_task": tables.success_table(per_task, tasks), "per_suite": suite_table(per_task, tasks)}


def suite_table(rates: Mapping[str, Mapping[str, Sequence[float]]], tasks: Sequence[str]) -> dict:
  """The paper's LIBERO layout: a row per policy, a column per suite (its tasks' mean success,
  computed per seed) and `Avg.` over the suites, each mean +- SE over seeds (%). A row without
  some suite (trained on others) has None there and no Avg."""
  by_suite: dict = {}
  for t in tasks:
    by_suite.setdefault(suites.parse(t).suite, []).append(t)
  titles = [suites.TITLES[s] for s in by_suite]
  rows = {}
  for policy, per_task in rates.items():
    mine = {s: ts for s, ts in by_suite.items() if all(t in per_task for t in ts)}
    n = len(per_task[next(iter(mine.values()))[0]]) if mine else 0
    suite_means = {s: [100 * float(np.mean([per_task[t][k] for t in ts])) for k in range(n)] for s, ts in mine.items()}
    cells = {suites.TITLES[s]: tables.mean_se(suite_means[s]) if s in mine else None for s in by_suite}
    cells["Avg."] = (tables.mean_se([float(np.mean([suite_means[s][k] for s in by_suite])) for k in range(n)])
                     if len(mine) == len(by_suite) else None)
    rows[policy] = {"cells": cells, "seeds": n}
  return {"suites": titles, "tasks": {suites.TITLES[s]: ts for s, ts in by_suite.items()}, "rows": rows}


def markdown(table: dict, paper: str | None = None) -> str:
  """A per-suite table (`suite_table`) as markdown: mean +- SE (%), the SE left out for one seed.
  With `paper` ("pretrain" or "fewshot") the paper's rows of that stage follow ours, in the same
  columns ("-" where it reports none; its Avg. is the mean of its suites', with no SE, when it
  reports every suite of ours)."""
  cols = table["suites"] + ["Avg."]
  lines = ["| policy | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
  fmt = lambda mean, se: f"{mean:.1f}" if se is None else f"{mean:.1f} ± {se:.1f}"
  for policy, row in table["rows"].items():
    lines.append(f"| {policy} | " + " | ".join("-" if row["cells"][c] is None else fmt(*row["cells"][c])
                                               for c in cols) + " |")
  if paper is not None:
    if paper not in PAPER:
      raise ValueError(f"the paper's LIBERO table has stages {', '.join(PAPER)}, not {paper!r}")
    for policy, row in PAPER[paper].items():
      cells = [fmt(*row[c]) if c in row else "-" for c in table["suites"]]
      full = all(c in row for c in table["suites"])
      cells.append(f"{np.mean([row[c][0] for c in table['suites']]):.1f}" if full else "-")
      lines.append(f"| paper: {policy} | " + " | ".join(cells) + " |")
  return "\n".join(lines)

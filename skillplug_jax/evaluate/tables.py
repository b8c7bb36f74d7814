"""Result tables in the paper's layout: a row per method, a column per task abbreviation, and Avg.

A row is one training configuration (`groups`: K=2 and K=4 are two rows);
its training seeds are aggregated. A cell is the mean over training seeds
+- its standard error (sample std / sqrt(n)); with one seed the SE is not
defined and only the mean is shown; '-' where no seed has a value. Avg is
computed per seed (mean over tasks) and then aggregated the same way, as
the paper does.

Three tables: success rate (%); policy queries per successful episode (each
seed's mean over its successful trials); and the same over paired trials
only, the trials every compared run solved, so that a method is not
credited with few queries for solving only the easy starts.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np

import envs
from skillplug_jax import diagnostics
from skillplug_jax.evaluate import groups


def mean_se(values: Sequence[float]) -> tuple[float, float | None]:
  n = len(values)
  if n == 0:
    raise ValueError("no values to aggregate")
  mean = sum(values) / n
  if n == 1:
    return mean, None
  var = sum((v - mean) ** 2 for v in values) / (n - 1)
  return mean, math.sqrt(var / n)


def abbr(task: str) -> str:
  """A task's column heading: its abbreviation (the toy's tasks: their primitive sequence, A>T>B)."""
  from envs import toy_skills
  from envs.libero import suites as libero_suites
  if task in toy_skills.TASK_IDS:
    return toy_skills.task_name(toy_skills.TASK_IDS[task])
  if libero_suites.is_libero(task):
    return libero_suites.abbr(task)
  return envs.task_class(task).abbr


def success_table(rates: Mapping[str, Mapping[str, Sequence[float]]], tasks: Sequence[str]) -> dict:
  """rates[policy][task] = success rate (0-1) of each training seed, seeds in the same order. A row
  may hold some of `tasks` only (an arm trained on another suite): '-' on the others, its Avg. over
  its own."""
  table = {"tasks": list(tasks), "abbr": [abbr(t) for t in tasks], "rows": {}}
  for policy, per_task in rates.items():
    own = [t for t in tasks if t in per_task]
    if not own:
      raise ValueError(f"{policy}: no result on any of {', '.join(tasks)}")
    seeds = {len(per_task[t]) for t in own}
    if len(seeds) != 1:
      raise ValueError(f"{policy}: tasks have different numbers of seeds ({sorted(seeds)})")
    n = seeds.pop()
    row = {t: mean_se([100 * r for r in per_task[t]]) if t in per_task else None for t in tasks}
    row["Avg."] = mean_se([100 * sum(per_task[t][s] for t in own) / len(own) for s in range(n)])
    table["rows"][policy] = {"cells": row, "seeds": n}
  return table


def _seed_means(episodes: Sequence[tuple[Sequence[bool], Sequence[float]]],
                only: np.ndarray | None = None) -> list[float | None]:
  """Each seed's mean queries over its successful trials, of those in `only` if given (None: no such trial)."""
  out = []
  for success, queries in episodes:
    keep = np.asarray(success, bool) & (True if only is None else only)
    out.append(float(np.asarray(queries, float)[keep].mean()) if keep.any() else None)
  return out


def _mean_se_or_none(values: Sequence[float | None]) -> tuple[float, float | None] | None:
  values = [v for v in values if v is not None]
  return mean_se(values) if values else None


def queries_table(episodes: Mapping[str, Mapping[str, Sequence[tuple[Sequence[bool], Sequence[float]]]]],
                  tasks: Sequence[str], paired: bool = False) -> dict:
  """Mean policy queries per successful episode, per row and task.

  episodes[row][task] = one (success [trials], queries [trials]) per
  training seed, seeds in the same order for every task; trial i is the
  same initial state in every run (`protocol`). A seed's value is its mean
  over its successful trials; a cell aggregates the seeds that have one
  (their number is in `n`). Avg: per seed, the mean over the tasks where it
  has a value.

  paired: trial i of a task counts only if every run in `episodes` (every
  seed of every row) solved it, so all runs are averaged over the same
  initial states; `paired_trials[task]` says how many there are.
  """
  table = {"tasks": list(tasks), "abbr": [abbr(t) for t in tasks], "rows": {},
           "paired": paired}
  shared = {}
  if paired:
    for t in tasks:
      solved = [np.asarray(s, bool) for per_task in episodes.values() if t in per_task for s, _ in per_task[t]]
      if len({len(s) for s in solved}) != 1:
        raise ValueError(f"{t}: runs have different numbers of trials; paired trials need the same")
      shared[t] = np.logical_and.reduce(solved)
    table["paired_trials"] = {t: int(shared[t].sum()) for t in tasks}
    table["trials"] = {t: int(shared[t].size) for t in tasks}
  for name, per_task in episodes.items():
    own = [t for t in tasks if t in per_task]  # a row may hold some tasks only ('-' on the others)
    seeds = {len(per_task[t]) for t in own}
    if len(seeds) != 1:
      raise ValueError(f"{name}: tasks have different numbers of seeds ({sorted(seeds)})")
    n = seeds.pop()
    per_seed = {t: _seed_means(per_task[t], shared.get(t)) for t in own}
    row = {t: _mean_se_or_none(per_seed[t]) if t in per_seed else None for t in tasks}
    avg = []
    for s in range(n):
      vals = [per_seed[t][s] for t in own if per_seed[t][s] is not None]
      avg.append(sum(vals) / len(vals) if vals else None)
    row["Avg."] = _mean_se_or_none(avg)
    counts = {t: sum(v is not None for v in per_seed[t]) if t in per_seed else 0 for t in tasks}
    counts["Avg."] = sum(v is not None for v in avg)
    table["rows"][name] = {"cells": row, "seeds": n, "n": counts}
  return table


def summarise(results: Sequence[Mapping[str, Any]], tasks: Sequence[str],
              row_tasks: Callable[[Mapping[str, Any]], Sequence[str]] | None = None) -> dict:
  """The rows and the three tables from per-(run, task) results.

  Each result carries `config` (its training key), `train_seed`, `task`,
  `success_rate`, `trial_success` and `trial_queries` (`protocol`). Every
  seed of a row must have a result on each task the row is evaluated on:
  all of `tasks`, or, with `row_tasks` (a row's training key -> its tasks;
  arms that train on different suites), those of `tasks` it names.
  """
  rows = groups.group_rows(results)
  by = {}
  for r in results:
    at = (groups.key_id(r["config"]), r["train_seed"], r["task"])
    if at in by:
      raise ValueError(f"{r['task']} was evaluated twice for one configuration and seed "
                       f"{r['train_seed']} ({by[at].get('run')} and {r.get('run')})")
    by[at] = r
  rates, episodes, own = {}, {}, {}
  for name, row in rows.items():
    i = groups.key_id(row["config"])
    mine = set(tasks if row_tasks is None else row_tasks(row["config"]))
    own[name] = [t for t in tasks if t in mine]
    if not own[name]:
      raise ValueError(f"{name}: is evaluated on none of {', '.join(tasks)}")
    for t in own[name]:
      missing = [s for s in row["seeds"] if (i, s, t) not in by]
      if missing:
        raise ValueError(f"{name}: seed(s) {missing} have no result on {t}")
      per_seed = [by[(i, s, t)] for s in row["seeds"]]
      rates.setdefault(name, {})[t] = [r["success_rate"] for r in per_seed]
      episodes.setdefault(name, {})[t] = [(r["trial_success"], r["trial_queries"]) for r in per_seed]
  out = dict(rows=rows, table=success_table(rates, tasks), queries=queries_table(episodes, tasks),
             queries_paired=queries_table(episodes, tasks, paired=True))
  diag = {}
  for name, row in rows.items():
    diag.update(routing_diagnostics({name: {s: [by[(groups.key_id(row["config"]), s, t)] for t in own[name]]
                                            for s in row["seeds"]}}, own[name]))
  if diag:
    out["diagnostics"] = diag
  return out


DIAGNOSTICS = ("usage_entropy", "routing_entropy_per_query", "effective_skills")  # evaluate/routing.py


def routing_diagnostics(results: Mapping[str, Mapping[Any, Sequence[Mapping[str, Any]]]],
                        tasks: Sequence[str]) -> dict:
  """The routing diagnostics of each row whose results carry them (ACT+SkillPlug).

  results[row][seed] = that seed's result per task, in `tasks` order. Per
  row: `seeds`, each seed's statistics over all its tasks' queries
  (`diagnostics.combine_tasks`, with the mutual information between task
  and skill); `mean`, their mean and SE over seeds; `tasks`, each task's
  statistics as mean and SE over seeds.
  """
  out = {}
  for name, per_seed in results.items():
    have = {s: [r.get("diagnostics") for r in rs] for s, rs in per_seed.items()}
    have = {s: ds for s, ds in have.items() if all(d and d.get("queries") for d in ds)}
    if not have:
      continue
    seeds = [dict(train_seed=s, **diagnostics.combine_tasks(ds)) for s, ds in have.items()]
    keys = DIAGNOSTICS + ("task_skill_mi", "task_skill_mi_norm")
    out[name] = dict(
        seeds=seeds, mean={k: mean_se([d[k] for d in seeds]) for k in keys},
        tasks={t: {k: mean_se([ds[i][k] for ds in have.values()]) for k in DIAGNOSTICS}
               for i, t in enumerate(tasks)})
  return out


def _cell(cell) -> str:
  if cell is None:
    return "-"
  mean, se = cell
  return f"{mean:.1f}" if se is None else f"{mean:.1f}±{se:.1f}"


def markdown(table: dict) -> str:
  """The table; a paired queries table adds a line with its paired-trial counts."""
  head = ["Method"] + table["abbr"] + ["Avg."]
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for name, row in table["rows"].items():
    cells = [_cell(row["cells"][t]) for t in table["tasks"]] + [_cell(row["cells"]["Avg."])]
    lines.append("| " + " | ".join([name] + cells) + " |")
  if "paired_trials" in table:
    lines += ["", "Trials every run solved: " + ", ".join(
        f"{a} {table['paired_trials'][t]}/{table['trials'][t]}" for t, a in zip(table["tasks"], table["abbr"]))]
  return "\n".join(lines)


def report(summary: dict, what: str) -> str:
  """The three tables of `summarise` as Markdown, each under a title; `what` says what was run."""
  return "\n".join([
      f"Success rate (%), {what}; mean±SE over training seeds where there are several:", "",
      markdown(summary["table"]), "",
      "Policy queries per successful episode (each seed's mean over its successful trials; "
      "mean±SE over seeds):", "",
      markdown(summary["queries"]), "",
      "Policy queries per successful episode over the paired trials (those every run above solved):", "",
      markdown(summary["queries_paired"])])


def _csv_field(text: str) -> str:
  return '"' + text.replace('"', '""') + '"' if "," in text or '"' in text else text


def csv(table: dict) -> str:
  head = ["method", "seeds"] + [f"{a}_mean,{a}_se" for a in table["abbr"]] + ["avg_mean,avg_se"]
  lines = [",".join(head)]
  for name, row in table["rows"].items():
    vals = [_csv_field(name), str(row["seeds"])]
    for key in list(table["tasks"]) + ["Avg."]:
      mean, se = row["cells"][key] or (None, None)
      vals += ["" if mean is None else f"{mean:.2f}", "" if se is None else f"{se:.2f}"]
    lines.append(",".join(vals))
  return "\n".join(lines) + "\n"

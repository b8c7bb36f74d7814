"""Success tables in the paper's layout: rows are policies, columns task abbreviations and Avg.

A cell is the mean success rate (%) over training seeds +- its standard
error (sample std / sqrt(n)); with one seed the SE is not defined and only
the mean is shown. Avg is computed per seed (mean over tasks) and then
aggregated the same way, as the paper does.
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import envs


def mean_se(values: Sequence[float]) -> tuple[float, float | None]:
  n = len(values)
  if n == 0:
    raise ValueError("no values to aggregate")
  mean = sum(values) / n
  if n == 1:
    return mean, None
  var = sum((v - mean) ** 2 for v in values) / (n - 1)
  return mean, math.sqrt(var / n)


def success_table(rates: Mapping[str, Mapping[str, Sequence[float]]], tasks: Sequence[str]) -> dict:
  """rates[policy][task] = success rate (0-1) of each training seed, seeds in the same order."""
  table = {"tasks": list(tasks), "abbr": [envs.task_class(t).abbr for t in tasks], "rows": {}}
  for policy, per_task in rates.items():
    seeds = {len(per_task[t]) for t in tasks}
    if len(seeds) != 1:
      raise ValueError(f"{policy}: tasks have different numbers of seeds ({sorted(seeds)})")
    n = seeds.pop()
    row = {t: mean_se([100 * r for r in per_task[t]]) for t in tasks}
    row["Avg."] = mean_se([100 * sum(per_task[t][s] for t in tasks) / len(tasks) for s in range(n)])
    table["rows"][policy] = {"cells": row, "seeds": n}
  return table


def _cell(mean: float, se: float | None) -> str:
  return f"{mean:.1f}" if se is None else f"{mean:.1f}±{se:.1f}"


def markdown(table: dict) -> str:
  head = ["Method"] + table["abbr"] + ["Avg."]
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for policy, row in table["rows"].items():
    cells = [_cell(*row["cells"][t]) for t in table["tasks"]] + [_cell(*row["cells"]["Avg."])]
    lines.append("| " + " | ".join([policy] + cells) + " |")
  return "\n".join(lines)


def csv(table: dict) -> str:
  head = ["method", "seeds"] + [f"{a}_mean,{a}_se" for a in table["abbr"]] + ["avg_mean,avg_se"]
  lines = [",".join(head)]
  for policy, row in table["rows"].items():
    vals = [policy, str(row["seeds"])]
    for key in list(table["tasks"]) + ["Avg."]:
      mean, se = row["cells"][key]
      vals += [f"{mean:.2f}", "" if se is None else f"{se:.2f}"]
    lines.append(",".join(vals))
  return "\n".join(lines) + "\n"

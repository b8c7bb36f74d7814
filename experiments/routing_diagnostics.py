"""python -m experiments.routing_diagnostics ROUTING_DIR [--out FILE_STEM]

The routing diagnostics (skillplug_jax/diagnostics.py) of a published run's
routing arrays, for committed runs whose checkpoints are not in the
repository (docs/results/<experiment>/routing/: index.json and one .npz per
policy, seed, stage and task, routing [trials, queries, K], NaN past each
trial's last query).

Per run (variant, policy, seed, stage), over every closed-loop query of every trial:
  usage_entropy        H(mean r) / log K        (1: every skill used alike)
  routing_entropy_per_query  mean H(r) / log K  (1: every query uniform)
  effective_skills     exp H(mean r)
  task_skill_mi_norm   I(task; skill) / min(log K, log tasks)
and, ours, whether routing follows the phases of an episode:
  phase_skill_mi_norm  I(phase; skill) / min(log K, log phases) within each task, averaged
                       over tasks (phase: the query's quarter of its episode)
  within_episode_tv    mean total-variation distance between a query's weights and its
                       episode's mean weights (0: one routing for the whole episode)
Writes FILE_STEM.json and FILE_STEM.md (default: ROUTING_DIR/../routing_diagnostics).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from skillplug_jax import diagnostics
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic

PHASES = 4


def episode_queries(routing: np.ndarray) -> list[np.ndarray]:
  """The valid queries [Q_i, K] of each trial (rows before the NaN padding)."""
  r = np.asarray(routing, np.float64)
  return [ep[np.isfinite(ep).all(-1)] for ep in r]


def task_stats(routing: np.ndarray) -> dict:
  """One task's numbers from its routing array [trials, queries, K]."""
  episodes = [e for e in episode_queries(routing) if len(e)]
  if not episodes:
    raise ValueError("no valid routing rows (every query is NaN)")
  queries = np.concatenate(episodes)
  stats = diagnostics.routing_stats(jnp.asarray(queries))
  phase_sum = np.zeros((PHASES, queries.shape[-1]))
  phase_count = np.zeros(PHASES)
  tv = []
  for ep in episodes:
    phase = np.minimum((np.arange(len(ep)) * PHASES) // len(ep), PHASES - 1)
    np.add.at(phase_sum, phase, ep)
    phase_count += np.bincount(phase, minlength=PHASES)
    tv.append(0.5 * np.abs(ep - ep.mean(0)).sum(-1).mean())
  phase_mean = phase_sum / np.maximum(phase_count, 1)[:, None]
  return dict(queries=int(len(queries)), mean_weights=np.asarray(stats["mean_weights"]).tolist(),
              routing_entropy_per_query=float(stats["routing_entropy_per_query"]), usage_entropy=float(stats["usage_entropy"]),
              phase_skill_mi_norm=_phase_mi_norm(phase_mean, phase_count),
              phase_routing=phase_mean.tolist(), within_episode_tv=float(np.mean(tv)))


def _phase_mi_norm(phase_mean: np.ndarray, phase_count: np.ndarray) -> float:
  """Normalised I(phase; skill) from the mean routing of each phase and its number of queries:
  `diagnostics.combine_tasks` with the phases as the 'tasks'."""
  parts = [dict(queries=n, mean_weights=m, routing_entropy_per_query=0.0) for m, n in zip(phase_mean, phase_count) if n > 0]
  return diagnostics.combine_tasks(parts)["task_skill_mi_norm"]


def run_diagnostics(routing_dir: Path) -> dict:
  index_path = routing_dir / "index.json"
  if not index_path.exists():
    raise FileNotFoundError(f"{index_path} not found: expected a published routing folder (index.json + .npz)")
  groups = defaultdict(dict)
  for entry in json.loads(index_path.read_text()):
    with np.load(routing_dir / entry["file"]) as z:
      key = (entry.get("variant", ""), entry["policy"], entry["seed"], entry["stage"])
      groups[key][entry["task"]] = task_stats(z["routing"])
  runs = []
  for (variant, policy, seed, stage), tasks in sorted(groups.items()):
    combined = diagnostics.combine_tasks(list(tasks.values()))
    weights = np.asarray([t["queries"] for t in tasks.values()], np.float64)
    combined.update(
        phase_skill_mi_norm=float(np.average([t["phase_skill_mi_norm"] for t in tasks.values()], weights=weights)),
        within_episode_tv=float(np.average([t["within_episode_tv"] for t in tasks.values()], weights=weights)))
    runs.append(dict(variant=variant, policy=policy, seed=seed, stage=stage, **combined, tasks=tasks))
  return dict(source=str(routing_dir), phases=PHASES, runs=runs)


def markdown(result: dict) -> str:
  lines = [f"Routing diagnostics of {result['source']} (closed-loop queries of every trial; "
           f"phase = quarter of the episode):", "",
           "| variant | policy | seed | stage | tasks | H(r)/log K | H(mean r)/log K | eff. skills | task-skill NMI | "
           "phase-skill NMI | within-episode TV | mean routing |", "|---" * 12 + "|"]
  for r in result["runs"]:
    lines.append(f"| {r['variant'] or '-'} | {r['policy']} | {r['seed']} | {r['stage']} | {int(r['num_tasks'])} | {r['routing_entropy_per_query']:.3f} | "
                 f"{r['usage_entropy']:.3f} | {r['effective_skills']:.2f} | {r['task_skill_mi_norm']:.3f} | "
                 f"{r['phase_skill_mi_norm']:.3f} | {r['within_episode_tv']:.3f} | "
                 + " / ".join(f"{w:.2f}" for w in r["mean_weights"]) + " |")
  return "\n".join(lines) + "\n"


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[1].replace("\n", " "))
  p.add_argument("routing_dir", help="a published routing folder (index.json and .npz files)")
  p.add_argument("--out", default="", help="file stem for .json and .md (default: ROUTING_DIR/../routing_diagnostics)")
  args = p.parse_args(argv)
  routing_dir = Path(args.routing_dir)
  stem = Path(args.out) if args.out else routing_dir.parent / "routing_diagnostics"
  result = run_diagnostics(routing_dir)
  write_json_atomic(stem.with_suffix(".json"), result)
  table = markdown(result)
  write_text_atomic(stem.with_suffix(".md"), table)
  print(table)
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""python -m experiments.routing_curves RUN [RUN ...] --out FILE_STEM [--every 100]

The routing over training (issue 43): is a router that ends uniform still
learning, or settled? Read from each run's training log (metrics.jsonl, the
batch diagnostics `diagnostics.training_metrics` logs every `log_every`
steps), per run:
  routing_entropy_per_query  mean H(r) / log K over the batch (1: uniform)
  effective_skills           exp H(mean r)
  task_skill_mi_norm         I(task; skill) / min(log K, log tasks), a batch estimate
                             (biased upwards by the few queries per task)
  label_skill_mi_norm        I(mined phase; skill), the same way, where the run loaded
                             phase labels (train.skill_labels)
Writes FILE_STEM.json (every logged step of every run), FILE_STEM.md (a
table every `--every` steps, default a tenth of the longest run) and
FILE_STEM.png (one panel per statistic, the step axis of each run scaled to
its own length beside the absolute one).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.train import run_files
from skillplug_jax.train.scalars import read_metrics

STATISTICS = ("routing_entropy_per_query", "effective_skills", "task_skill_mi_norm", "label_skill_mi_norm")


def run_label(run: Path) -> str:
  """<variant>/<run folder>: the arm (the pipeline's OUT/<variant>/runs/<run>) and the run."""
  return f"{run.parent.parent.name}/{run.name}" if run.parent.name == "runs" else run.name


def curves(run: Path) -> dict:
  """Every logged step's routing statistics of one run: {"steps": [...], name: [...]}."""
  rows = [m for m in read_metrics(run) if "diag/routing_entropy_per_query" in m]
  if not rows:
    raise ValueError(f"{run}: its training log has no routing diagnostics (an ACT run, or one logged "
                     "before they existed)")
  cfg = run_files.read_config(run)
  out = dict(run=str(run), label=run_label(run), max_steps=cfg.max_steps, steps=[int(m["step"]) for m in rows])
  for name in STATISTICS:
    values = [m.get(f"diag/{name}") for m in rows]
    if any(v is not None for v in values):
      out[name] = [None if v is None else float(v) for v in values]
  return out


def table(all_curves: list[dict], every: int) -> str:
  """Markdown: for each run, the statistics at every `every` steps (the logged step nearest)."""
  lines = []
  for c in all_curves:
    names = [n for n in STATISTICS if n in c]
    lines += [f"### {c['label']}", "", "| step | " + " | ".join(names) + " |", "|" + "---|" * (len(names) + 1)]
    steps = np.asarray(c["steps"])
    for want in [int(steps.min())] + list(range(every, int(steps.max()) + 1, every)):
      i = int(np.abs(steps - want).argmin())
      lines.append(f"| {steps[i]} | " + " | ".join(f"{c[n][i]:.3f}" for n in names) + " |")
    lines.append("")
  return "\n".join(lines)


def plot(all_curves: list[dict], path: Path) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  names = [n for n in STATISTICS if any(n in c for c in all_curves)]
  fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
  for ax, name in zip(axes[0], names):
    for c in all_curves:
      if name in c:
        ax.plot(c["steps"], c[name], label=c["label"], lw=1)
    top = max(max(v for v in c[name] if v is not None) for c in all_curves if name in c)
    # on the statistic's whole range, so that near-uniform routing looks it
    ax.set_ylim(*{"routing_entropy_per_query": (0, 1.05), "effective_skills": (0.9, max(top, 1) * 1.05 + 0.1)}.get(
        name, (0, max(0.05, 1.1 * top))))
    ax.set_title(name, fontsize=9)
    ax.set_xlabel("training step")
    ax.grid(alpha=0.3)
  axes[0][0].legend(fontsize=6)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("runs", nargs="+", type=Path, help="ACT+SkillPlug run directories (their metrics.jsonl)")
  p.add_argument("--out", required=True, type=Path, help="FILE_STEM: writes FILE_STEM.json, .md and .png")
  p.add_argument("--every", type=int, default=0, help="the table's step interval (default: a tenth of the longest run)")
  args = p.parse_args(argv)
  try:
    all_curves = [curves(r) for r in args.runs]
  except (ValueError, FileNotFoundError) as e:
    print(f"routing_curves: error: {e}", file=sys.stderr)
    return 2
  longest = max(max(c["steps"]) for c in all_curves)
  every = args.every or max(longest // 10, 1)
  args.out.parent.mkdir(parents=True, exist_ok=True)
  write_json_atomic(args.out.with_suffix(".json"), dict(statistics=list(STATISTICS), curves=all_curves))
  write_text_atomic(args.out.with_suffix(".md"), "# Routing over training\n\n"
                    + "Batch diagnostics of the training log (experiments/routing_curves.py).\n\n"
                    + table(all_curves, every))
  plot(all_curves, args.out.with_suffix(".png"))
  print(f"wrote {args.out}.json, .md and .png ({len(all_curves)} runs)")
  return 0


if __name__ == "__main__":
  sys.exit(main())

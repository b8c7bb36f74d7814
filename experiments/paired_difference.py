"""python -m experiments.paired_difference --a FILE[:SECTION] --b FILE[:SECTION] [--match-a S] [--match-b S]

The difference between two arms' closed-loop success, paired trial for
trial and seed for seed: what issue 27 asks to report beside each variant.

FILE is an evaluation or few-shot JSON (`skillplug eval/fewshot --out`) or a
pipeline summary.json; SECTION picks `pretrain` or `fewshot` in a summary.
`--match-a/--match-b` keep the results whose run directory contains the
text (one arm of a summary holding several); `--variant-a/--variant-b` those
of one variant of a summary (its `variant` field: arms that adapt another's
runs share that arm's run directories). Trial i of a task is the same
start in both arms (the evaluation seed fixes it), and seed s of one arm is
paired with seed s of the other.

Per seed: each arm's average over tasks and their difference B - A; over
seeds: the mean difference +- its standard error (sample std / sqrt(n
seeds)). With one seed the SE over seeds is not defined, and the SE over
trials (std of the paired per-trial differences / sqrt(n trials), all
tasks pooled) is given instead: it measures the evaluation's noise only,
not the training seed's, so it is no test of the method.
Writes OUT.json and OUT.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.evaluate.tables import mean_se


def load_arm(spec: str, match: str = "", variant: str = "") -> dict:
  """{(seed, task): trial_success array} of one arm, from FILE[:SECTION]."""
  path, _, section = spec.partition(":")
  data = json.loads(Path(path).read_text())
  results = data[section]["results"] if section else data["results"]
  arm = {}
  for r in results:
    if (match and match not in str(r.get("run", ""))) or (variant and r.get("variant") != variant):
      continue
    key = (int(r.get("train_seed", 0)), r["task"])
    if key in arm:
      raise ValueError(f"{spec}: two results for seed {key[0]} on {key[1]}; narrow them with --match")
    arm[key] = np.asarray(r["trial_success"], float)
  if not arm:
    raise ValueError(f"{spec}: no results" + (f" whose run contains {match!r}" if match else "")
                     + (f" of variant {variant!r}" if variant else ""))
  return arm


def paired_difference(a: dict, b: dict) -> dict:
  """B - A over the (seed, task) pairs both arms have, trial by trial (percentage points)."""
  keys = sorted(set(a) & set(b))
  if not keys:
    raise ValueError(f"the arms share no (seed, task): A has {sorted(a)}, B has {sorted(b)}")
  for k in keys:
    if a[k].shape != b[k].shape:
      raise ValueError(f"seed {k[0]} on {k[1]}: {a[k].size} trials against {b[k].size}; pairs need equal counts")
  seeds, tasks = sorted({s for s, _ in keys}), sorted({t for _, t in keys})
  missing = [(s, t) for s in seeds for t in tasks if (s, t) not in a or (s, t) not in b]
  if missing:
    raise ValueError(f"not every seed has every task in both arms: missing {missing}")
  per_task = {t: {"a": 100 * float(np.mean([a[s, t].mean() for s in seeds])),
                  "b": 100 * float(np.mean([b[s, t].mean() for s in seeds]))} for t in tasks}
  per_seed = {s: {"a": 100 * float(np.mean([a[s, t].mean() for t in tasks])),
                  "b": 100 * float(np.mean([b[s, t].mean() for t in tasks]))} for s in seeds}
  for row in list(per_task.values()) + list(per_seed.values()):
    row["diff"] = row["b"] - row["a"]
  diff, se = mean_se([per_seed[s]["diff"] for s in seeds])
  trial_diffs = 100 * np.concatenate([b[k] - a[k] for k in keys])
  se_trials = float(trial_diffs.std(ddof=1) / math.sqrt(trial_diffs.size)) if trial_diffs.size > 1 else None
  return dict(seeds=seeds, tasks=tasks, trials=int(a[keys[0]].size), per_task=per_task,
              per_seed={str(s): v for s, v in per_seed.items()}, diff=diff, se_over_seeds=se,
              se_over_trials=se_trials)


def markdown(d: dict, label_a: str, label_b: str) -> str:
  lines = [f"B - A: B = {label_b}, A = {label_a}; {d['trials']} paired trials per task, seeds {d['seeds']}.", "",
           "| task | A | B | B - A |", "|---|---|---|---|"]
  lines += [f"| {t} | {v['a']:.1f} | {v['b']:.1f} | {v['diff']:+.1f} |" for t, v in d["per_task"].items()]
  lines += ["", "| seed | A avg. | B avg. | B - A |", "|---|---|---|---|"]
  lines += [f"| {s} | {v['a']:.1f} | {v['b']:.1f} | {v['diff']:+.1f} |" for s, v in d["per_seed"].items()]
  se = (f"± {d['se_over_seeds']:.1f} (SE over {len(d['seeds'])} seeds)" if d["se_over_seeds"] is not None
        else f"(one seed: SE over trials {d['se_over_trials']:.1f}, the evaluation's noise only)")
  lines += ["", f"Difference of the averages: {d['diff']:+.1f} {se}."]
  return "\n".join(lines) + "\n"


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--a", required=True, help="FILE[:SECTION] of arm A (the reference)")
  p.add_argument("--b", required=True, help="FILE[:SECTION] of arm B")
  p.add_argument("--match-a", default="", help="keep A's results whose run directory contains this")
  p.add_argument("--match-b", default="", help="keep B's results whose run directory contains this")
  p.add_argument("--variant-a", default="", help="keep A's results of this variant (a summary's)")
  p.add_argument("--variant-b", default="", help="keep B's results of this variant")
  p.add_argument("--label-a", default="A")
  p.add_argument("--label-b", default="B")
  p.add_argument("--out", required=True, help="write OUT.json and OUT.md")
  args = p.parse_args(argv)
  try:
    d = paired_difference(load_arm(args.a, args.match_a, args.variant_a),
                          load_arm(args.b, args.match_b, args.variant_b))
  except (ValueError, KeyError, FileNotFoundError) as e:
    p.error(str(e))
  d.update(a=dict(spec=args.a, match=args.match_a, variant=args.variant_a, label=args.label_a),
           b=dict(spec=args.b, match=args.match_b, variant=args.variant_b, label=args.label_b))
  text = markdown(d, args.label_a, args.label_b)
  write_json_atomic(Path(f"{args.out}.json"), d)
  write_text_atomic(Path(f"{args.out}.md"), text)
  print(text + f"wrote {args.out}.json, .md")
  return 0


if __name__ == "__main__":
  sys.exit(main())

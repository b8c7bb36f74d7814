"""Evaluation at scale: every task, many trials, memory bounded by the batch.

    python -m benchmarks.bench_eval_scale --trials 1000 --batch 50 --out results/bench_eval_scale.json
    python -m benchmarks.bench_eval_scale --run results/runs/<run> --trials 1000   # a trained policy

One state policy (a trained run, or the quick preset's ACT with random
weights: its episodes run to the time limit, the slowest case) evaluated
closed loop on each task of `--taskset` for `--trials` paired trials,
`--batch` environments at a time, as `skillplug eval` does. Each batch size
runs in its own process, so that its peak RSS is its own. Records wall time,
trials/s and peak RSS per batch size, and checks that the first
`--prefix` trials equal a `--prefix`-trial evaluation of the same policy.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

from skillplug_jax.atomic_json import write_json_atomic


def _controller(run: str):
  import jax

  import envs
  from skillplug_jax import experiment
  from skillplug_jax.evaluate.policy_controller import load_controller, policy_controller
  from skillplug_jax.train import loop
  if run:
    return load_controller(Path(run))[0]
  cfg = experiment.preset("quick", "act")
  params = loop.init_params(cfg, jax.random.PRNGKey(0))
  stats = {"action": {"mean": list(envs.robot.HOME_QPOS), "std": [0.01] * 7},  # small moves about home
           "joint_pos": {"mean": [0.0] * 7, "std": [1.0] * 7},
           "object_state": {"mean": [0.0] * envs.OBJECT_STATE_DIM, "std": [1.0] * envs.OBJECT_STATE_DIM}}
  return policy_controller(cfg.model, params, stats)


def bench_one(run: str, tasks: list[str], trials: int, batch: int, prefix: int) -> dict:
  """In this process: every task, `trials` at `batch`; then the `prefix`-trial check."""
  from tqdm import tqdm

  from skillplug_jax.evaluate import protocol
  controller = _controller(run)
  bar = tqdm(total=len(tasks) * trials, desc=f"eval batch {batch}", unit="trial", file=sys.stderr)
  per_task, prefix_equal = {}, {}
  for task in tasks:
    t = time.time()
    r = protocol.evaluate_task(task, controller, trials, batch=batch, backend="mujoco", on_batch=bar.update)
    per_task[task] = dict(success_rate=r["success_rate"], wall_s=round(time.time() - t, 1))  # the check apart
    if prefix:
      short = protocol.evaluate_task(task, controller, prefix, batch=prefix, backend="mujoco")
      prefix_equal[task] = all(r[k][:prefix] == short[k] for k in ("trial_success", "trial_queries",
                                                                   "trial_success_step"))
  bar.close()
  wall = sum(v["wall_s"] for v in per_task.values())
  return dict(batch=batch, trials=trials, tasks=len(tasks), wall_s=round(wall, 1),
              peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
              per_task=per_task, prefix_equal=prefix_equal)


def main(argv=None) -> int:
  import envs
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--run", default="", help="a trained state run (default: random weights, quick preset ACT)")
  p.add_argument("--taskset", default="discoverse7,discoverse_fewshot4", help="tasksets or task names, comma-separated (default: all 11 tasks)")
  p.add_argument("--trials", type=int, default=1000)
  p.add_argument("--batches", default="50", help="batch sizes, each in its own process, e.g. 25,100")
  p.add_argument("--prefix", type=int, default=50, help="check the first N trials against an N-trial run (0: skip)")
  p.add_argument("--out", default="results/bench_eval_scale.json")
  p.add_argument("--one", type=int, default=0, help=argparse.SUPPRESS)  # internal: run one batch size here
  args = p.parse_args(argv)
  tasks = [n for part in args.taskset.split(",") for n in envs.taskset(part)]
  if args.one:
    print(json.dumps(bench_one(args.run, tasks, args.trials, args.one, args.prefix)))
    return 0
  rows = []
  for batch in [int(b) for b in args.batches.split(",")]:
    cmd = [sys.executable, "-m", "benchmarks.bench_eval_scale", "--one", str(batch), "--run", args.run,
           "--taskset", args.taskset, "--trials", str(args.trials), "--prefix", str(args.prefix)]
    out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=True).stdout
    rows.append(json.loads(out.strip().splitlines()[-1]))
    r = rows[-1]
    print(f"batch {batch}: {r['tasks']} tasks x {r['trials']} trials in {r['wall_s']:.0f} s "
          f"({r['tasks'] * r['trials'] / r['wall_s']:.1f} trials/s), peak RSS {r['peak_rss_mb']:.0f} MB, "
          f"first {args.prefix} trials equal: {all(r['prefix_equal'].values()) if r['prefix_equal'] else '-'}")
  from skillplug_jax.startup import cpu_name
  write_json_atomic(Path(args.out), dict(run=args.run or "random weights, quick preset ACT", taskset=args.taskset,
                                         cpu=cpu_name(), rows=rows))
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

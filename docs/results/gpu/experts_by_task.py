"""`skillplug experts` one task at a time in one process (skillplug_jax.cli.cmd_experts itself), the
combined JSON rewritten after each task, so that a timeout keeps the tasks already done.

    python experts_by_task.py --taskset discoverse7 --episodes 100 --batch 100 --backend mjx-warp --json OUT.json
"""
import argparse
import json
import os
import sys
import tempfile

import envs
from skillplug_jax import cli
from skillplug_jax.atomic_json import write_json_atomic

p = argparse.ArgumentParser()
p.add_argument("--taskset", required=True)
p.add_argument("--episodes", type=int, default=100)
p.add_argument("--batch", type=int, default=100)
p.add_argument("--seed", type=int, default=0)
p.add_argument("--backend", default="mjx-warp")
p.add_argument("--json", required=True)
a = p.parse_args()
names = [n for part in a.taskset.split(",") for n in envs.taskset(part)]
combined = None
for name in names:
  one = os.path.join(tempfile.gettempdir(), f"experts_{name}.json")
  cli.cmd_experts(argparse.Namespace(taskset=name, episodes=a.episodes, batch=a.batch, seed=a.seed,
                                     backend=a.backend, json=one))
  part = json.load(open(one))
  if combined is None:
    combined = dict(part, taskset=a.taskset, tasks=[],
                    command="skillplug experts (cmd_experts per task) " + " ".join(sys.argv[1:]))
  combined["tasks"] += part["tasks"]
  write_json_atomic(a.json, combined)
print(f"wrote {a.json} ({len(combined['tasks'])} tasks)")

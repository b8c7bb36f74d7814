"""Short sweep of the SkillPlug loss weights (the paper gives no values).

    python -m experiments.sweep_loss_weights --out docs/results/loss_weights/sweep_loss_weights_quick_cpu.json

One weight at a time around the defaults (kl 1, bsa 0.1, sd 0.1), each run the
`quick` preset (state only, discoverse7, 10 demos per task, 1500 steps).
The criterion is the held-out action error of the inference path
(`Policy.predict`: no posterior, CVAE latent zero): mean L1 on normalised
actions over every timestep of demonstrations from unseen initial states
(`--val-demos` per task, data seed 1). Also reported: the final training
terms, the routing entropy on held-out states (log K = uniform routing) and
the mean off-diagonal skill similarity. A small proxy: closed-loop success
is the real criterion once budgets allow it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from skillplug_jax import losses
from skillplug_jax.experiment import preset
from skillplug_jax.data import loader as data_loader
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import config, loop
from skillplug_jax.train.scalars import read_metrics
from skillplug_jax.atomic_json import write_json_atomic

GRID = {"kl": (0.1, 10.0), "bsa": (0.01, 1.0), "sd": (0.01, 1.0)}


def held_out(run_dir, val: data_loader.Demonstrations) -> dict:
  cfg, params, _ = loop.load_params(run_dir)
  val = dataclasses.replace(val, stats=json.loads((run_dir / "norm_stats.json").read_text()))
  ld = data_loader.ChunkLoader(val, batch_size=1, chunk=cfg.model.chunk,
                               normalize_object_state=cfg.model.normalize_object_state)
  ep = np.repeat(np.arange(val.num_episodes), val.length)
  t = np.concatenate([np.arange(n) for n in val.length])
  batch = {k: jnp.asarray(v) for k, v in ld.gather(ep, t).items()}
  pred, routing = jax.jit(lambda p, b: Policy(cfg.model).apply({"params": p}, b, method=Policy.predict))(params, batch)
  out = {"val_l1": float(losses.reconstruction_l1(pred, batch["actions"], batch["action_mask"])),
         "val_samples": int(len(ep))}
  if routing is not None:
    r = np.asarray(routing)
    out["routing_entropy"] = float(-(r * np.log(np.maximum(r, 1e-12))).sum(-1).mean())
    out["routing_mean"] = r.mean(0).round(3).tolist()
  return out


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--val-demos", type=int, default=3)
  p.add_argument("--workdir", default="results/runs/sweep")
  p.add_argument("--out", default="results/sweep_loss_weights.json")
  args = p.parse_args(argv)

  base = preset("quick", "skillplug")
  val_cfg = config.override(base, [f"demos={args.val_demos}", "data_seed=1"])
  val = loop.load_data(val_cfg)
  settings = [("default", [])] + [(f"{k}={v}", [f"loss.{k}={v}"]) for k, vals in GRID.items() for v in vals]
  rows = []
  for name, sets in settings:
    cfg = config.override(base, sets + [f"workdir={args.workdir}/{name}"])
    t0 = time.time()
    run = loop.train(cfg, progress=False)
    last = read_metrics(run)[-1]
    row = dict(setting=name, loss=dict(kl=cfg.loss.kl, bsa=cfg.loss.bsa, sd=cfg.loss.sd),
               train={k.split("/")[1]: round(v, 4) for k, v in last.items() if k.startswith("loss/")},
               wall_s=round(time.time() - t0, 1), **held_out(run, val))
    rows.append(row)
    print(json.dumps(row), flush=True)
  result = dict(preset="quick", steps=base.max_steps, val=dict(demos=args.val_demos, data_seed=1),
                device=str(jax.devices()[0]), results=rows)
  write_json_atomic(args.out, result)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()

"""Training-step benchmark: steps/s and samples/s for ACT and ACT+SkillPlug.

    make bench-train        # or: python -m experiments.bench_train --presets quick,paper --out results/bench_train.json

Times the jitted train step alone (forward, four-term loss, backward, AdamW)
on a synthetic batch already on the devices, so the number is the model's
cost; compare it with `bench_loader`'s batches/s to see whether the loader
keeps up. The SkillPlug overhead is its step time over ACT's at the same
preset and batch. Each number is the median of `--steps` timed steps after a
compile step.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from skillplug_jax.train import config, loop
from skillplug_jax.atomic_json import write_json_atomic


def bench_one(preset: str, policy: str, batch: int, steps: int) -> dict:
  cfg = config.override(config.preset(preset, policy), [f"batch_size={batch}"])
  mesh = Mesh(np.asarray(jax.devices()), ("data",))
  repl, data = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec("data"))
  key = jax.random.PRNGKey(0)
  params = loop.init_params(cfg, key)
  n_params = sum(x.size for x in jax.tree.leaves(params))
  tx = loop.optimizer(cfg, params)
  state = jax.device_put(loop.TrainState(jnp.zeros((), jnp.int32), params, tx.init(params)), repl)
  rng = np.random.default_rng(0)
  b = {k: np.array(v) for k, v in loop.example_batch(cfg, batch).items()}
  for k, v in b.items():
    if v.dtype == np.float32:
      b[k] = rng.normal(size=v.shape).astype(np.float32)
    elif v.dtype == np.uint8:
      b[k] = rng.integers(0, 256, size=v.shape, dtype=np.uint8)
  b["action_mask"][:, -5:] = False
  b = jax.device_put(b, data)
  step = jax.jit(loop.make_train_step(cfg, tx, key), donate_argnums=0, out_shardings=(repl, repl))
  t = time.perf_counter()
  state, m = step(state, b)
  jax.block_until_ready(m)
  compile_s = time.perf_counter() - t
  times = []
  for _ in range(steps):
    t = time.perf_counter()
    state, m = step(state, b)
    jax.block_until_ready(m)
    times.append(time.perf_counter() - t)
  dt = statistics.median(times)
  row = dict(preset=preset, policy=policy, batch=batch, images=cfg.model.use_images,
             hidden=cfg.model.hidden, params_m=round(n_params / 1e6, 2), compile_s=round(compile_s, 1),
             step_ms=round(1000 * dt, 1), steps_per_s=round(1 / dt, 2), samples_per_s=round(batch / dt, 1))
  print(json.dumps(row), flush=True)
  return row


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--presets", default="quick,paper")
  p.add_argument("--batch", type=int, default=0, help="batch size (0: each preset's own)")
  p.add_argument("--steps", type=int, default=5)
  p.add_argument("--out", default="results/bench_train.json")
  args = p.parse_args(argv)
  rows = []
  for preset in args.presets.split(","):
    batch = args.batch or config.preset(preset).batch_size
    pair = {pol: bench_one(preset, pol, batch, args.steps) for pol in ("act", "skillplug")}
    pair["skillplug"]["overhead_vs_act"] = round(pair["skillplug"]["step_ms"] / pair["act"]["step_ms"], 3)
    rows += [pair["act"], pair["skillplug"]]
  result = dict(devices=[str(d) for d in jax.devices()], xla_flags=os.environ.get("XLA_FLAGS", ""),
                results=rows)
  write_json_atomic(args.out, result)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()

"""Loader benchmark: batches/s of the chunked loader, on the host and onto the devices.

    make bench-loader DATASET=results/datasets/<name>
    python -m benchmarks.bench_loader --dataset DIR --batches 16,256 --out results/bench_loader.json

Three numbers per batch size: `load_s` (decode the dataset once), `host_batches_per_s`
(sampling and gathering numpy batches, one thread), and
`device_batches_per_s` (the prefetching iterator, batches sharded onto the
devices and waited for). Compare the last with the training step's rate: if
the loader is faster, the accelerator never waits for data.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

from skillplug_jax.data import loader
from skillplug_jax.atomic_json import write_json_atomic


def bench(dataset: str, batches: list[int], steps: int, images: bool) -> dict:
  t0 = time.perf_counter()
  demos = loader.load_demonstrations(dataset, images=images)
  load_s = time.perf_counter() - t0
  rows = []
  for b in batches:
    ld = loader.ChunkLoader(demos, batch_size=b, images=images)
    ld.numpy_batch(0)
    t = time.perf_counter()
    for s in range(steps):
      ld.numpy_batch(s)
    host = steps / (time.perf_counter() - t)
    first = next(ld.iterate(num_steps=1))  # compile-free warm-up of the transfer path
    jax.block_until_ready(first)
    t = time.perf_counter()
    for batch in ld.iterate(num_steps=steps):
      jax.block_until_ready(batch)
    dev = steps / (time.perf_counter() - t)
    mb = sum(v.nbytes for v in ld.numpy_batch(0).values()) / 2**20
    rows.append(dict(batch=b, host_batches_per_s=round(host, 1), device_batches_per_s=round(dev, 1),
                     samples_per_s=round(dev * b, 1), batch_mb=round(mb, 3)))
    print(json.dumps(rows[-1]), flush=True)
  return dict(dataset=os.path.abspath(dataset), images=images, episodes=demos.num_episodes,
              steps=int(demos.length.sum()), load_s=round(load_s, 2), devices=[str(d) for d in jax.devices()],
              results=rows)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--dataset", required=True, help="dataset directory written by `skillplug demos`")
  p.add_argument("--batches", default="16,256")
  p.add_argument("--steps", type=int, default=200, help="batches timed per batch size")
  p.add_argument("--state-only", action="store_true", help="do not load or batch images")
  p.add_argument("--out", default="results/bench_loader.json")
  args = p.parse_args(argv)
  result = bench(args.dataset, [int(b) for b in args.batches.split(",")], args.steps, not args.state_only)
  write_json_atomic(args.out, result)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()

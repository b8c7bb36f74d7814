"""Training and inference benchmark of ACT and ACT+SkillPlug, beside LeRobot's ACT.

    make bench-train        # or: python -m benchmarks.bench_train --presets quick,paper --out results/bench_train.json
    make bench-train REF_PYTHON=/path/to/lerobot-venv/bin/python   # LeRobot's ACT before and after ours

Per preset and policy, each in its own process (so peak memory is its own):
the jitted train step (forward, losses, backward, AdamW) on a synthetic
batch already on the devices: median step time, samples/s, compile time,
the compiled step's XLA buffers and the process's peak RSS; and the jitted
inference call `Policy.predict(obs) -> chunk` at batch 1 and 64 (median).
The SkillPlug overhead (`overhead_vs_act`) is the median ratio of its step
time to ACT's with the two steps alternated in one more process
(`--pair-rounds`; `paired` in the JSON); the ratio of the separate runs'
medians is kept as `overhead_vs_act_separate`.

With `--reference PYTHON` (a Python that has LeRobot; see
../shared/tools/ref_act_bench.py for how to build one, outside the project),
LeRobot's ACT is timed at the paper shapes before and after ours, in the
same run, and the JSON records both and our speed-up against each.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from skillplug_jax import experiment
from skillplug_jax.atomic_json import write_json_atomic
from skillplug_jax.train import config

REFERENCE_TOOL = Path(__file__).resolve().parents[2] / "shared" / "tools" / "ref_act_bench.py"


def _median_ms(fn, calls: int) -> tuple[float, float]:
  times = []
  for _ in range(calls):
    t = time.perf_counter()
    fn()
    times.append(time.perf_counter() - t)
  return 1000 * statistics.median(times), 1000 * min(times)


def _synthetic_batch(cfg, size: int) -> dict:
  """A batch of `size` with random contents and the last 5 steps padded."""
  import numpy as np

  from skillplug_jax.train import loop
  rng = np.random.default_rng(0)
  b = {k: np.array(v) for k, v in loop.example_batch(cfg, size).items()}
  for k, v in b.items():
    if v.dtype == np.float32:
      b[k] = rng.normal(size=v.shape).astype(np.float32)
    elif v.dtype == np.uint8:
      b[k] = rng.integers(0, 256, size=v.shape, dtype=np.uint8)
  b["action_mask"][:, -5:] = False
  return b


def _compiled_step(preset: str, policy: str, batch: int):
  """The jitted train step of (preset, policy) on a synthetic batch already on
  the devices. Returns (cfg, one_step() that runs a step and waits for it,
  compile seconds, XLA memory analysis, parameter count, a getter of the
  current parameters)."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  from jax.sharding import Mesh, NamedSharding, PartitionSpec

  from skillplug_jax.train import loop

  cfg = config.override(experiment.preset(preset, policy), [f"batch_size={batch}"])
  mesh = Mesh(np.asarray(jax.devices()), ("data",))
  repl, data = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec("data"))
  key = jax.random.PRNGKey(0)
  params = loop.init_params(cfg, key)
  n_params = sum(x.size for x in jax.tree.leaves(params))
  tx = loop.optimizer(cfg, params, cfg.num_steps(1))
  state = jax.device_put(loop.TrainState(jnp.zeros((), jnp.int32), params, tx.init(params)), repl)
  b = jax.device_put(_synthetic_batch(cfg, batch), data)
  t = time.perf_counter()
  step = jax.jit(loop.make_train_step(cfg, tx, key), donate_argnums=0, out_shardings=(repl, repl))
  compiled = step.lower(state, b).compile()
  compile_s = time.perf_counter() - t
  holder = [state]

  def one_step():
    holder[0], m = compiled(holder[0], b)
    jax.block_until_ready(m)

  return cfg, one_step, compile_s, compiled.memory_analysis(), n_params, lambda: holder[0].params


def bench_one(preset: str, policy: str, batch: int, steps: int, infer_batches: tuple[int, ...],
              infer_calls: int) -> dict:
  """One preset and policy, in the calling process."""
  import jax

  from skillplug_jax.model.policy import Policy

  cfg, one_step, compile_s, mem, n_params, current_params = _compiled_step(preset, policy, batch)
  t = time.perf_counter()
  one_step()  # the first call also allocates; not timed
  if steps <= 0:  # about 20 s of timed steps, at least 10
    steps = int(min(max(20 / (time.perf_counter() - t), 10), 300))
  usage = resource.getrusage(resource.RUSAGE_SELF)
  step_ms, step_min_ms = _median_ms(one_step, steps)
  after = resource.getrusage(resource.RUSAGE_SELF)

  model = Policy(cfg.model)
  predict = jax.jit(lambda p, obs: model.apply({"params": p}, obs, method=Policy.predict)[0])
  params = current_params()
  infer = {}
  for size in infer_batches:
    obs = {k: v for k, v in _synthetic_batch(cfg, size).items()
           if k not in ("actions", "action_mask", "task_id")}
    obs = jax.device_put(obs)
    t = time.perf_counter()
    jax.block_until_ready(predict(params, obs))
    first_s = time.perf_counter() - t
    ms, _ = _median_ms(lambda: jax.block_until_ready(predict(params, obs)), infer_calls)
    infer[str(size)] = dict(ms=round(ms, 2), compile_s=round(first_s, 1))

  return dict(preset=preset, policy=policy, batch=batch, images=cfg.model.use_images,
              hidden=cfg.model.hidden, params_m=round(n_params / 1e6, 2), compile_s=round(compile_s, 1),
              step_ms=round(step_ms, 1), step_min_ms=round(step_min_ms, 1), steps=steps,
              steps_per_s=round(1000 / step_ms, 2), samples_per_s=round(1000 * batch / step_ms, 1),
              xla_temp_mb=round(mem.temp_size_in_bytes / 2**20, 1) if mem else None,
              xla_args_mb=round(mem.argument_size_in_bytes / 2**20, 1) if mem else None,
              peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
              # the kernel's share: page faults of buffers mapped afresh each call (Makefile's GLIBC_TUNABLES)
              minor_faults_per_step=round((after.ru_minflt - usage.ru_minflt) / steps),
              cpu_ms_per_step=dict(user=round(1000 * (after.ru_utime - usage.ru_utime) / steps, 1),
                                   sys=round(1000 * (after.ru_stime - usage.ru_stime) / steps, 1)),
              infer_ms={k: v["ms"] for k, v in infer.items()},
              infer_compile_s={k: v["compile_s"] for k, v in infer.items()})


def bench_pair(preset: str, batch: int, rounds: int) -> dict:
  """ACT's and ACT+SkillPlug's steps alternated in one process, `rounds` of
  each: the overhead ratio compares steps taken seconds apart, so a machine
  that speeds up or slows down during the run (this VM drifts by 10-20% over
  minutes) shifts both alike, where separate processes run minutes apart."""
  steps = {}
  for policy in ("act", "skillplug"):
    _, one_step, *_ = _compiled_step(preset, policy, batch)
    one_step()  # allocation, not timed
    steps[policy] = one_step
  if rounds <= 0:  # about 20 s of alternated steps, 10 to 300 rounds
    t = time.perf_counter()
    for one_step in steps.values():
      one_step()
    rounds = int(min(max(20 / (time.perf_counter() - t), 10), 300))
  times = {policy: [] for policy in steps}
  for _ in range(rounds):
    for policy, one_step in steps.items():
      t = time.perf_counter()
      one_step()
      times[policy].append(time.perf_counter() - t)
  med = {policy: 1000 * statistics.median(v) for policy, v in times.items()}
  paired = [s / a for a, s in zip(times["act"], times["skillplug"])]
  return dict(preset=preset, batch=batch, rounds=rounds,
              act_step_ms=round(med["act"], 1), skillplug_step_ms=round(med["skillplug"], 1),
              ratio_of_medians=round(med["skillplug"] / med["act"], 3),
              median_paired_ratio=round(statistics.median(paired), 3),
              paired_ratio_range=[round(min(paired), 3), round(max(paired), 3)])


def _child(queue, fn, args):
  try:
    queue.put(fn(*args))
  except BaseException as e:  # noqa: BLE001 - reported by the parent
    queue.put(e)


def bench_in_process(fn, *args) -> dict:
  """`fn(*args)` (bench_one, bench_pair) in a fresh process: its own peak RSS
  and compile caches."""
  ctx = mp.get_context("spawn")
  queue = ctx.Queue()
  proc = ctx.Process(target=_child, args=(queue, fn, args))
  proc.start()
  result = queue.get()
  proc.join()
  if isinstance(result, BaseException):
    raise RuntimeError(f"{fn.__name__}{args[:2]} failed: {result!r}") from result
  print(json.dumps(result), flush=True)
  return result


def reference(python: str, steps: int, tunables: str = "") -> dict:
  """LeRobot's ACT at the paper shapes (ref_act_bench.py), its JSON line.

  `tunables`: GLIBC_TUNABLES for its process; by default none, as LeRobot's
  users run it (ours may have the Makefile's, which the JSON records).
  """
  if not REFERENCE_TOOL.exists():
    raise FileNotFoundError(f"the reference benchmark {REFERENCE_TOOL} is missing")
  cmd = [python, str(REFERENCE_TOOL), "--dec-layers", "7", "--steps", str(steps), "--warmup", "2"]
  env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
  if tunables:
    env["GLIBC_TUNABLES"] = tunables
  print("reference:", *([f"GLIBC_TUNABLES={tunables}"] if tunables else []), *cmd, flush=True)
  out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
  row = json.loads(out.stdout.strip().splitlines()[-1])
  row["glibc_tunables"] = tunables
  print(json.dumps({k: row[k] for k in ("train_step_ms_median", "samples_per_s", "infer_ms_b1", "infer_ms_b64")}),
        flush=True)
  return row


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--presets", default="quick,paper")
  p.add_argument("--policies", default="act,skillplug")
  p.add_argument("--batch", type=int, default=0, help="batch size (0: each preset's own)")
  p.add_argument("--steps", type=int, default=0,
                 help="timed train steps, median reported (0: about 20 s of them, at least 10)")
  p.add_argument("--pair-rounds", type=int, default=0,
                 help="rounds of ACT's and ACT+SkillPlug's steps alternated in one process for the "
                      "overhead ratio (0: about 20 s of them, at least 10; -1: none, only the ratio "
                      "of the separate runs)")
  p.add_argument("--infer-batches", default="1,64")
  p.add_argument("--infer-calls", type=int, default=20, help="timed inference calls per batch (median)")
  p.add_argument("--reference", metavar="PYTHON", default=os.environ.get("REF_PYTHON", ""),
                 help="a Python with LeRobot: time its ACT (paper shapes) before and after ours")
  p.add_argument("--reference-steps", type=int, default=10)
  p.add_argument("--out", default="results/bench_train.json")
  args = p.parse_args(argv)

  infer_batches = tuple(int(x) for x in args.infer_batches.split(",") if x)
  refs = [reference(args.reference, args.reference_steps)] if args.reference else []
  rows = []
  for preset in args.presets.split(","):
    batch = args.batch or experiment.preset(preset).batch_size
    pair = {pol: bench_in_process(bench_one, preset, pol, batch, args.steps, infer_batches,
                                  args.infer_calls)
            for pol in args.policies.split(",")}
    if "act" in pair and "skillplug" in pair:
      sp = pair["skillplug"]
      sp["overhead_vs_act_separate"] = round(sp["step_ms"] / pair["act"]["step_ms"], 3)
      if args.pair_rounds >= 0:
        sp["paired"] = bench_in_process(bench_pair, preset, batch, args.pair_rounds)
        sp["overhead_vs_act"] = sp["paired"]["median_paired_ratio"]
    rows += list(pair.values())
  tunables = os.environ.get("GLIBC_TUNABLES", "")
  tuned_refs = []
  if args.reference:
    refs.append(reference(args.reference, args.reference_steps))
    if tunables:  # and LeRobot with the allocator settings ours ran with
      tuned_refs.append(reference(args.reference, args.reference_steps, tunables))

    def speedups(row, against):
      return [dict(samples_per_s=round(row["samples_per_s"] / r["samples_per_s"], 2),
                   infer_b1=round(r["infer_ms_b1"] / row["infer_ms"]["1"], 2)
                   if "1" in row["infer_ms"] else None) for r in against]

    for row in rows:
      if row["preset"] == "paper":
        row["vs_reference"] = speedups(row, refs)
        if tuned_refs:
          row["vs_reference_same_tunables"] = speedups(row, tuned_refs)
  import jax
  result = dict(devices=[str(d) for d in jax.devices()], cpu=platform.processor() or platform.machine(),
                cpu_count=os.cpu_count(), xla_flags=os.environ.get("XLA_FLAGS", ""),
                glibc_tunables=tunables,
                jax=jax.__version__, command=" ".join([sys.executable, "-m", "benchmarks.bench_train"] + (argv or sys.argv[1:])),
                results=rows, reference=refs, reference_same_tunables=tuned_refs)
  write_json_atomic(args.out, result)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()

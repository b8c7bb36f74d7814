"""Environment benchmark: physics steps/s, control steps/s and render frames/s per task and batch.

    make bench-envs          # or: python -m experiments.bench_envs --out results/bench_envs.json

Steps/s count environment steps summed over the batch. Physics steps are bare
`mjx.step` calls; control steps are full env steps at 20 Hz (physics substeps,
success check, observations), with the arm holding its home pose and objects
resting, so contacts are those of a settled scene. Each number is the best of
`--repeats` timed runs after a compile run.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
from mujoco import mjx

import envs
from envs import robot, rollout
from skillplug_jax.atomic_json import write_json_atomic


def _best_time(fn, arg, repeats):
  jax.block_until_ready(fn(arg))  # compile
  best = float("inf")
  for _ in range(repeats):
    t = time.perf_counter()
    jax.block_until_ready(fn(arg))
    best = min(best, time.perf_counter() - t)
  return best


def bench_task(name, batch, steps, repeats, render_size):
  env = envs.make(name, num_envs=batch, render=render_size is not None,
                  image_size=render_size or (64, 64))
  task = env.env
  state = jax.jit(env.reset)(rollout.reset_keys(0, batch))
  hold = jnp.tile(jnp.asarray(robot.HOME_QPOS, jnp.float32), (batch, 1))

  @jax.jit
  def control(s):
    return jax.lax.scan(lambda s, _: (env.step(s, hold), None), s, None, length=steps)[0].done

  row = dict(task=name, batch=batch)
  if render_size is None:
    mx = task.mjx_model
    step = jax.vmap(lambda d: mjx.step(mx, d))

    @jax.jit
    def physics(d):
      return jax.lax.scan(lambda d, _: (step(d), None), d, None, length=steps * task.n_substeps)[0].qpos

    t = _best_time(physics, state.pipeline_state, repeats)
    row["physics_steps_per_s"] = round(batch * steps * task.n_substeps / t, 1)
    t = _best_time(control, state, repeats)
    row["control_steps_per_s"] = round(batch * steps / t, 1)
  else:
    t = _best_time(control, state, repeats)
    row["render_size"] = list(render_size)
    row["control_steps_per_s_with_2_cameras"] = round(batch * steps / t, 1)
  return row


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--tasks", default="all", help="comma-separated task names, or 'all'")
  p.add_argument("--batches", default="16,64,256")
  p.add_argument("--render-batches", default="16,64", help="batches for the rendering runs ('' skips)")
  p.add_argument("--render-size", default="64x64", help="HxW of the rendered images")
  p.add_argument("--steps", type=int, default=10, help="control steps per timed run")
  p.add_argument("--repeats", type=int, default=2)
  p.add_argument("--out", default="results/bench_envs.json")
  args = p.parse_args(argv)
  envs.quiet_warp()

  names = list(envs.TASKS) if args.tasks == "all" else [envs.task_class(n).name for n in args.tasks.split(",")]
  size = tuple(int(v) for v in args.render_size.split("x"))
  rows = []
  for name in names:
    for b in [int(v) for v in args.batches.split(",") if v]:
      rows.append(bench_task(name, b, args.steps, args.repeats, None))
      print(json.dumps(rows[-1]), flush=True)
  for b in [int(v) for v in args.render_batches.split(",") if v]:
    rows.append(bench_task(names[0], b, args.steps, args.repeats, size))
    print(json.dumps(rows[-1]), flush=True)

  m = envs.task_class(names[0])().mj_model.opt
  options = dict(impl="warp", timestep=m.timestep, control_dt=envs.EnvConfig.control_dt,
                 iterations=int(m.iterations), ls_iterations=int(m.ls_iterations),
                 cone="elliptic", impratio=float(m.impratio), integrator="implicitfast",
                 contacts_per_env=envs.EnvConfig.contacts_per_env,
                 constraints_per_env=envs.EnvConfig.constraints_per_env)
  out = dict(device=str(jax.devices()[0]), platform=jax.devices()[0].platform,
             cpu_count=os.cpu_count(), mjx_options=options, results=rows)
  write_json_atomic(args.out, out)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()

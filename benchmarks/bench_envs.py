"""Both physics backends side by side, and the wall time of a closed-loop evaluation on the C one.

    make bench-envs          # or: python -m benchmarks.bench_envs --out results/bench_envs.json

Why: the project runs its tasks on MuJoCo's C engine ("mujoco", `mujoco.batch`
on the CPU's threads) or on MJX-Warp ("mjx-warp", for accelerators). This
measures, on this machine, how much faster the C engine is, and whether the
paper's evaluation protocol fits in two minutes on it.

1. Throughput, per task, batch and camera mode (state only, or both 64x64
   cameras rendered every control step), for each backend:
   - physics steps/s: bare physics steps (`Batch.step` in C, vmapped
     `mjx.step` for MJX-Warp), `n_substeps` (10) per call; measured in state
     mode only (rendering does not touch the physics);
   - control steps/s: full env steps at 20 Hz (physics substeps, success
     check, observations, images).
   Steps/s are summed over the batch. Each run resets, takes one warm-up step
   (compiling: reported as compile_s = warm-up time - one timed step; Warp
   loads its kernels from its disk cache, so a first-ever run compiles longer) and then
   times a fixed number of steps, the arm holding its home pose, so no episode
   ends and the contacts are those of a settled scene. MJX-Warp is ~100x
   slower on a CPU, so it gets fewer timed steps (--warp-steps), and by default
   it renders at batches 16 and 64 only (--warp-render-batches).
2. The wall time of the paper's protocol (11 tasks x 50 trials, batch 50,
   `evaluate_task`) on the C backend with an untrained state policy (ACT,
   quick model config). An untrained policy succeeds in (almost) no episode,
   so every batch runs to its task's time limit: the worst case for wall time.
   Compilation is included (it is part of what an evaluation costs).
3. Targets, each with its measured value and pass/fail: C >= 50x MJX-Warp's
   control steps/s at batch 64, state only, per task and overall (geometric
   mean over tasks); C >= 2x MJX-Warp with both cameras (batch 64); the 11 x
   50 evaluation <= 120 s. Without batch 64 in --batches, the largest batch
   measured stands in; a smaller evaluation than 11 x 50 gets no pass/fail.

Others may share the machine: the load average is recorded before and after.
"""

from __future__ import annotations

import os

import envs  # first: it picks MUJOCO_GL (envs/headless.py) before mujoco is imported

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import datetime  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
from mujoco import mjx  # noqa: E402

from envs import robot, rollout  # noqa: E402
from skillplug_jax.atomic_json import write_json_atomic  # noqa: E402
from skillplug_jax.evaluate.policy_controller import policy_controller  # noqa: E402
from skillplug_jax.evaluate.protocol import evaluate_task  # noqa: E402
from skillplug_jax.experiment import preset  # noqa: E402
from skillplug_jax.train import loop  # noqa: E402
from skillplug_jax.train.config import TrainConfig  # noqa: E402

BACKENDS = ("mujoco", "mjx-warp")
TARGET_BATCH = 64
TARGETS = dict(state_ratio=50.0, cameras_ratio=2.0, eval_s=120.0)


def _timed(fn):
  t = time.perf_counter()
  out = jax.block_until_ready(fn())
  return out, time.perf_counter() - t


def measure(task, backend, batch, cameras, steps, image_size):
  """Steps/s of one backend on one task: control steps, and bare physics in state mode."""
  benv = envs.make(task, num_envs=batch, backend=backend, render=cameras, image_size=image_size)
  n_sub = benv.env.n_substeps
  hold = jnp.tile(jnp.asarray(robot.HOME_QPOS, jnp.float32), (batch, 1))
  if backend == "mujoco":  # not jittable: the physics runs in C
    reset, step = benv.reset, benv.step

    def physics(d):
      benv._batch.step(nstep=n_sub)
      return d
  else:
    reset, step = jax.jit(benv.reset), jax.jit(benv.step)
    one = jax.vmap(lambda d: mjx.step(benv.env.mjx_model, d))
    physics = jax.jit(lambda d: jax.lax.fori_loop(0, n_sub, lambda _, d: one(d), d))

  def run(fn, x):  # warm-up call, then `steps` timed calls
    x, first = _timed(lambda: fn(x))
    t = time.perf_counter()
    for _ in range(steps):
      x = fn(x)
    jax.block_until_ready(x)
    return x, first, (time.perf_counter() - t) / steps

  state, reset_s = _timed(lambda: reset(rollout.reset_keys(0, batch)))
  state, first, dt = run(lambda s: step(s, hold), state)
  row = dict(control_steps_per_s=round(batch / dt, 1), control_step_ms=round(1e3 * dt, 2),
             compile_s=round(max(first - dt, 0.0), 2), reset_s=round(reset_s, 2), timed_steps=steps,
             episodes_ended=int(jnp.sum(state.done > 0)))
  if not cameras:  # after the control steps: the C batch's state is the env's no more
    _, first, dt = run(physics, state.pipeline_state)
    row.update(physics_steps_per_s=round(batch * n_sub / dt, 1), physics_compile_s=round(max(first - dt, 0.0), 2))
  return row


def untrained_controller():
  """An untrained ACT state policy (quick config) whose actions stay near the home pose."""
  m = dataclasses.replace(preset("quick").model, policy="act")
  params = loop.init_params(TrainConfig(preset="quick", model=m), jax.random.PRNGKey(0))
  stats = {"action": {"mean": list(robot.HOME_QPOS), "std": [0.01] * 7},
           "joint_pos": {"mean": [0.0] * 7, "std": [1.0] * 7},
           "object_state": {"mean": [0.0] * envs.OBJECT_STATE_DIM, "std": [1.0] * envs.OBJECT_STATE_DIM}}
  return policy_controller(m, params, stats, name="untrained act")


def _ratio(row, key):
  c, w = row["mujoco"], row["mjx-warp"]
  return round(c[key] / w[key], 1) if c and w and key in c and key in w else None


def _target(rows, key, minimum):
  per_task = {r["task"]: r[key] for r in rows}
  vals = [v for v in per_task.values() if v]
  overall = round(math.exp(sum(map(math.log, vals)) / len(vals)), 1) if vals else None
  ok = lambda v: None if v is None else v >= minimum  # noqa: E731
  return dict(target=f"mujoco/mjx-warp control steps/s >= {minimum}", batch=rows[0]["batch"] if rows else None,
              per_task={t: dict(value=v, passed=ok(v)) for t, v in per_task.items()},
              overall=dict(value=overall, passed=ok(overall), how="geometric mean of the per-task ratios"))


def _fmt(v, digits=0):
  return "-" if v is None else f"{v:,.{digits}f}"


HEADER = ("| task | batch | cameras | C physics/s | Warp physics/s | C control/s | Warp control/s "
          "| C/Warp control | compile s C / Warp |\n|---|---|---|---|---|---|---|---|---|")


def markdown_row(r):
  c, w = r["mujoco"] or {}, r["mjx-warp"] or {}
  return (f"| {r['task']} | {r['batch']} | {r['cameras']} | {_fmt(c.get('physics_steps_per_s'))} "
          f"| {_fmt(w.get('physics_steps_per_s'))} | {_fmt(c.get('control_steps_per_s'))} "
          f"| {_fmt(w.get('control_steps_per_s'), 1)} | {_fmt(r['ratio_control'], 1)} "
          f"| {_fmt(c.get('compile_s'), 1)} / {_fmt(w.get('compile_s'), 1)} |")


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--tasks", default="all", help="comma-separated task names, or 'all' (default)")
  p.add_argument("--batches", default="16,64,256", help="batch sizes (default 16,64,256)")
  p.add_argument("--render", default="state,cameras",
                 help="camera modes: 'state' (no images), 'cameras' (side + wrist RGB), or both (default)")
  p.add_argument("--image-size", default="64x64", help="HxW of the rendered images (default 64x64)")
  p.add_argument("--steps", type=int, default=10, help="timed control steps per run on mujoco (default 10)")
  p.add_argument("--warp-steps", type=int, default=2, help="timed control steps per run on mjx-warp (default 2)")
  p.add_argument("--warp-render-batches", default="16,64",
                 help="batches at which mjx-warp renders ('all': every --batches; default 16,64)")
  p.add_argument("--eval-tasks", default="all", help="tasks of the evaluation timing, 'all' or 'none' (skip)")
  p.add_argument("--eval-trials", type=int, default=50, help="trials per task (default 50, the protocol's)")
  p.add_argument("--eval-batch", type=int, default=50, help="evaluation batch (default 50, the protocol's)")
  p.add_argument("--out", default="results/bench_envs.json")
  args = p.parse_args(argv)
  envs.quiet_warp()

  names = lambda s: list(envs.TASKS) if s == "all" else [] if s == "none" else [  # noqa: E731
      envs.task_class(n).name for n in s.split(",") if n]
  tasks, eval_tasks = names(args.tasks), names(args.eval_tasks)
  batches = [int(v) for v in args.batches.split(",") if v]
  warp_render = batches if args.warp_render_batches == "all" else [
      int(v) for v in args.warp_render_batches.split(",") if v]
  modes = [m for m in args.render.split(",") if m]
  if set(modes) - {"state", "cameras"}:
    p.error(f"--render takes 'state' and/or 'cameras', got {args.render!r}")
  size = tuple(int(v) for v in args.image_size.split("x"))
  ncpu = os.cpu_count()
  cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
             "unknown")
  out = dict(date=datetime.datetime.now().astimezone().isoformat(timespec="seconds"), cpu=cpu, cores=ncpu,
             jax=jax.__version__, mujoco=mujoco.__version__, jax_device=str(jax.devices()[0]),
             command="python -m benchmarks.bench_envs " + " ".join(sys.argv[1:] if argv is None else argv),
             loadavg_before=[round(v, 2) for v in os.getloadavg()],
             settings=dict(steps_mujoco=args.steps, steps_mjx_warp=args.warp_steps, image_size=list(size),
                           action="robot.HOME_QPOS held", mjx_warp_render_batches=warp_render,
                           control_dt_s=envs.EnvConfig.control_dt,
                           physics_substeps=round(envs.EnvConfig.control_dt / envs.EnvConfig.physics_timestep)),
             throughput=[], evaluation=None, targets=None)
  t_start = time.perf_counter()

  # 1. Throughput, both backends.
  rows = out["throughput"]
  print(HEADER, flush=True)
  for task in tasks:
    for mode in modes:
      cameras = mode == "cameras"
      for b in batches:
        row = dict(task=task, batch=b, cameras=2 if cameras else 0)
        for backend in BACKENDS:
          skip = backend == "mjx-warp" and cameras and b not in warp_render
          row[backend] = None if skip else measure(
              task, backend, b, cameras, args.steps if backend == "mujoco" else args.warp_steps, size)
        row["ratio_control"] = _ratio(row, "control_steps_per_s")
        row["ratio_physics"] = _ratio(row, "physics_steps_per_s")
        rows.append(row)
        print(markdown_row(row), flush=True)
        write_json_atomic(args.out, out)

  # 2. The closed-loop evaluation's wall time on the C backend.
  if eval_tasks:
    controller = untrained_controller()
    per_task, t0 = [], time.perf_counter()
    for task in eval_tasks:
      t = time.perf_counter()
      r = evaluate_task(task, controller, args.eval_trials, batch=args.eval_batch, backend="mujoco")
      wall = time.perf_counter() - t
      limit = round(envs.task_class(task).time_limit_s / envs.EnvConfig.control_dt)
      per_task.append(dict(task=task, wall_s=round(wall, 1), time_limit_steps=limit, successes=r["successes"],
                           nan_episodes=r["nan_episodes"],
                           env_steps_per_s_at_limit=round(args.eval_trials * limit / wall, 1)))
      print(f"eval {task}: {wall:.1f} s ({r['successes']}/{args.eval_trials} successes, "
            f"{limit} control steps per episode)", flush=True)
    total = time.perf_counter() - t0
    out["evaluation"] = dict(
        backend="mujoco", policy="untrained ACT state policy (quick model config)", trials=args.eval_trials,
        batch=args.eval_batch, tasks=eval_tasks, total_s=round(total, 1), per_task=per_task,
        full_protocol=set(eval_tasks) == set(envs.TASKS) and args.eval_trials == 50 and args.eval_batch == 50,
        note=("worst case: an untrained policy succeeds in (almost) no episode, so every batch runs to its "
              "task's time limit; a trained policy's batches end when all its episodes have succeeded. "
              "Compilation (per task: env bookkeeping, policy for the task's object-state width) is included."))

  # 3. Targets.
  tb = TARGET_BATCH if TARGET_BATCH in batches else max(batches, default=None)
  pick = lambda cams: [r for r in rows if r["batch"] == tb and r["cameras"] == cams]  # noqa: E731
  ev = out["evaluation"]
  out["targets"] = dict(
      state=_target(pick(0), "ratio_control", TARGETS["state_ratio"]),
      cameras=_target(pick(2), "ratio_control", TARGETS["cameras_ratio"]),
      evaluation=dict(target=f"11 tasks x 50 trials on mujoco <= {TARGETS['eval_s']:.0f} s",
                      value=ev and ev["total_s"],
                      passed=(ev["total_s"] <= TARGETS["eval_s"]) if ev and ev["full_protocol"] else None,
                      note=None if ev and ev["full_protocol"] else "not measured on the full protocol"))
  out["loadavg_after"] = [round(v, 2) for v in os.getloadavg()]
  out["wall_s"] = round(time.perf_counter() - t_start, 1)
  write_json_atomic(args.out, out)

  print(f"\n{HEADER}\n" + "\n".join(markdown_row(r) for r in rows))
  if ev:
    print("\n| eval task | wall s | successes |\n|---|---|---|")
    for r in ev["per_task"]:
      print(f"| {r['task']} | {r['wall_s']} | {r['successes']}/{args.eval_trials} |")
    print(f"| total | {ev['total_s']} | |")
  print("\n| target | value | passed |\n|---|---|---|")
  for key in ("state", "cameras"):
    t = out["targets"][key]
    print(f"| {t['target']} ({key}, batch {t['batch']}, overall) | {t['overall']['value']} "
          f"| {t['overall']['passed']} |")
  t = out["targets"]["evaluation"]
  print(f"| {t['target']} | {t['value']} | {t['passed']} |")
  print(f"\nload average before {out['loadavg_before']}, after {out['loadavg_after']}; "
        f"{out['wall_s']} s in all; wrote {args.out}")


if __name__ == "__main__":
  main()

"""LIBERO episodes per second: our C-engine batch against LIBERO's own env, on the same cores.

    python -m benchmarks.bench_libero --out results/bench_libero.json      # make bench-libero

For one task per suite, both run the benchmark's init states under the same fixed action
sequence (tests/test_libero_engine.actions) with both cameras at 128x128:
- ours: `engine.LiberoBatch` with `--batch` environments on every core (`nthread=0`), timed per
  control step as physics (controller included), cameras and the goal check; with the cameras
  drawn as the reference draws them and without multisampling, each on render threads and in
  render processes (one per core), and without cameras;
- the reference: OffScreenRenderEnv, one process per core (`--workers`), each running its share
  of `--ref-trials` trials as LIBERO's evaluation does (env.reset(), set_init_state, steps), with
  its cameras and with their observables disabled (compared with our state-only batch).
A trial's cost is its reset plus `time_limit` control steps at the measured rate (no policy: the
actions are scripted, so policy time is left out of both), and episodes per second is the
number of workers (or the batch) over that cost. `--steps` control steps are timed per trial.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import time

import envs  # noqa: F401  first: it picks MUJOCO_GL before mujoco is imported

import numpy as np  # noqa: E402

from envs.libero import engine, scene, suites  # noqa: E402

TASKS = (("libero_spatial", 4), ("libero_object", 0), ("libero_goal", 5), ("libero_10", 2))


def actions(steps: int, seed: int) -> np.ndarray:
  """The parity tests' motion (tests/test_libero_engine.py): smooth, turning, gripper toggling."""
  t = np.arange(steps)[:, None]
  phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, (1, 6))
  arm = np.array([[0.8, 0.8, 0.6, 0.3, 0.3, 0.4]]) * np.sin(t / 4.0 + phase)
  arm[t[:, 0] % 5 == 0, 3:] = 0.0
  return np.concatenate([arm, np.where((t[:, 0] // 8) % 2 == 1, 1.0, -1.0)[:, None]], axis=1)


# Our cameras: as the reference draws them; without multisampling (each on render threads, and in
# render processes: envs.render_process); none (state only).
OURS = {"reference_look": dict(render=True), "no_multisampling": dict(render=True, multisample=False),
        "reference_look_processes": dict(render=True, render_processes=True),
        "no_multisampling_processes": dict(render=True, multisample=False, render_processes=True),
        "no_cameras": dict(render=False)}


def ours(suite: str, index: int, batch: int, steps: int, mode: str) -> dict:
  s = scene.scene(suite, index)
  states = suites.init_states(suite, index)[np.arange(batch) % suites.INIT_STATES_PER_TASK]
  acts = actions(steps, index)
  b = engine.LiberoBatch(s, batch, nthread=0, **OURS[mode])
  try:
    t0 = time.perf_counter()
    b.reset(states)
    b.observe()
    reset_s = time.perf_counter() - t0
    physics = render = goal = 0.0
    for a in acts:
      t0 = time.perf_counter()
      b.step(np.repeat(a[None], batch, 0))
      t1 = time.perf_counter()
      b.observe()
      t2 = time.perf_counter()
      b.success()
      t3 = time.perf_counter()
      physics, render, goal = physics + t1 - t0, render + t2 - t1, goal + t3 - t2
  finally:
    b.close()
  step_s = (physics + render + goal) / steps
  limit = suites.TIME_LIMITS[suite]
  return {"batch": batch, "reset_s": reset_s, "control_step_s": step_s,
          "share": {"physics": physics / (physics + render + goal), "cameras": render / (physics + render + goal),
                    "goal": goal / (physics + render + goal)},
          "env_steps_per_s": batch / step_s, "episodes_per_s": batch / (reset_s + limit * step_s)}


def _reference_worker(args) -> dict:
  suite, index, trials, steps, cameras = args
  os.environ.setdefault("MUJOCO_GL", "egl")
  env = scene.reference_env(suite, index)
  if not cameras:
    for cam in scene.CAMERAS:
      env.env.modify_observable(f"{cam}_image", "enabled", False)
  try:
    acts = actions(steps, index)
    states = suites.init_states(suite, index)
    reset_s = step_s = 0.0
    for i in trials:
      t0 = time.perf_counter()
      env.reset()
      env.set_init_state(states[i])
      t1 = time.perf_counter()
      for a in acts:
        env.step(a)
      t2 = time.perf_counter()
      reset_s, step_s = reset_s + t1 - t0, step_s + t2 - t1
  finally:
    env.close()
  return {"trials": len(trials), "reset_s": reset_s, "step_s": step_s}


def reference(suite: str, index: int, trials: int, workers: int, steps: int, cameras: bool) -> dict:
  shares = [list(range(w, trials, workers)) for w in range(workers)]
  with mp.get_context("spawn").Pool(workers) as pool:
    parts = pool.map(_reference_worker, [(suite, index, share, steps, cameras) for share in shares])
  n = sum(p["trials"] for p in parts)
  reset_s = sum(p["reset_s"] for p in parts) / n
  step_s = sum(p["step_s"] for p in parts) / (n * steps)
  limit = suites.TIME_LIMITS[suite]
  return {"workers": workers, "trials": n, "reset_s": reset_s, "control_step_s": step_s,
          "env_steps_per_s": workers / step_s, "episodes_per_s": workers / (reset_s + limit * step_s)}


def cpu_model() -> str:
  try:
    with open("/proc/cpuinfo") as f:
      info = f.read()
    pick = lambda key: next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith(key)), "?")  # noqa: E731
    return f"{pick('model name')} (family {pick('cpu family')} model {pick('model')})"
  except OSError:
    return platform.processor()


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--batch", type=int, default=50, help="our environments per task (default 50: a task's init states)")
  parser.add_argument("--ref-trials", type=int, default=4, help="reference trials per task, over the workers")
  parser.add_argument("--workers", type=int, default=os.cpu_count(), help="reference processes (default: one per core)")
  parser.add_argument("--steps", type=int, default=20, help="control steps timed per trial")
  parser.add_argument("--out", default="results/bench_libero.json")
  args = parser.parse_args()
  rows = []
  for suite, index in TASKS:
    scene.scene(suite, index)  # built and cached before the clocks start
    row = {"suite": suite, "task": index, "time_limit": suites.TIME_LIMITS[suite],
           "ours": {mode: ours(suite, index, args.batch, args.steps, mode) for mode in OURS},
           "reference": {"cameras": reference(suite, index, args.ref_trials, args.workers, args.steps, True),
                         "no_cameras": reference(suite, index, args.ref_trials, args.workers, args.steps, False)}}
    ref_of = lambda mode: row["reference"]["no_cameras" if mode == "no_cameras" else "cameras"]  # noqa: E731
    row["speedup_episodes"] = {mode: r["episodes_per_s"] / ref_of(mode)["episodes_per_s"] for mode, r in row["ours"].items()}
    rows.append(row)
    print(f"{suite} {index}: episodes/s, ours (B={args.batch}) against the reference ({args.workers} processes): "
          + ", ".join(f"{mode} {r['episodes_per_s']:.3f} vs {ref_of(mode)['episodes_per_s']:.3f} "
                      f"(x{row['speedup_episodes'][mode]:.2f})" for mode, r in row["ours"].items()), flush=True)
  os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
  with open(args.out, "w") as f:
    json.dump({"cpu": cpu_model(), "cores": os.cpu_count(), "image_size": engine.IMAGE_SIZE,
               "args": vars(args), "tasks": rows}, f, indent=1)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()

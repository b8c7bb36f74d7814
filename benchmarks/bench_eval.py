"""Closed-loop evaluation benchmark: control steps/s with the policy in the loop vs the bare environment.

    make bench-eval      # or: python -m benchmarks.bench_eval --batches 16,64 --out results/bench_eval.json
    python -m benchmarks.bench_eval --presets budget --batches 512,1024   # on a GPU

Both numbers are environment control steps per second (batch x steps / time)
at the same batch and task, on one backend (`--backend`). "bare" steps the
environments with a fixed action (a jitted `lax.scan` of `env.step` on
MJX-Warp, a loop of C batch steps on `mujoco`); "policy" is the episode
engine (`envs/rollout.py`):
the policy queried every step with temporal ensembling, plus its
bookkeeping, and rendering where the preset reads images. Their ratio is
what the policy and the engine cost; `ms_per_step` also times the
controller alone (network, normalisation, ensembling; no physics) and the
engine with a controller that holds the pose (the bare run's physics with
the engine's bookkeeping), to split that cost: the physics of a moving arm
costs more or less than that of a held pose, so engine / bare also carries
a physics difference. The policy has random weights (the
cost does not depend on them) and the task's time limit is shortened to
`--steps` so every episode runs to it; each number is the best of
`--repeats` timed runs after a compile run, on one device.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp

import envs
from envs import robot, rollout as env_rollout
from envs.rollout import Controller, run_episodes as evaluate
from skillplug_jax import experiment
from skillplug_jax.atomic_json import write_json_atomic
from skillplug_jax.evaluate.policy_controller import policy_controller
from skillplug_jax.train import loop


def _short_env(task: str, steps: int, per_device: int, render: bool, image_size, backend: str):
  base = envs.task_class(task)
  short = type(base.__name__, (base,), {"time_limit_s": steps * envs.EnvConfig.control_dt})
  env = short(envs.EnvConfig(num_envs=per_device, backend=backend))
  return envs.batch_of(env, per_device, render=render, image_size=image_size)


def _best(fn, repeats: int) -> float:
  jax.block_until_ready(fn())  # compile
  best = float("inf")
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    best = min(best, time.perf_counter() - t0)
  return best


def bench(task: str, preset: str, policy: str, batch: int, steps: int, repeats: int, backend: str) -> dict:
  cfg = experiment.preset(preset, policy)
  m = cfg.model
  benv = _short_env(task, steps, batch, m.use_images, m.image_size, backend)
  keys = env_rollout.reset_keys(0, batch)
  params = loop.init_params(cfg, jax.random.PRNGKey(0))
  stats = {"action": {"mean": list(robot.HOME_QPOS), "std": [0.01] * 7},
           "joint_pos": {"mean": [0.0] * 7, "std": [1.0] * 7},
           "object_state": {"mean": [0.0] * envs.OBJECT_STATE_DIM, "std": [1.0] * envs.OBJECT_STATE_DIM}}
  controller = policy_controller(m, params, stats)

  out = {}

  def engine():
    out["r"] = evaluate(benv, controller, keys)
    return out["r"].success

  t_policy = _best(engine, repeats)
  ran = out["r"].steps_run
  # bare: the same environments stepped with a fixed action
  bare_env = _short_env(task, steps, batch, m.use_images, m.image_size, backend)
  hold = jnp.tile(jnp.asarray(robot.HOME_QPOS, jnp.float32), (batch, 1))
  if bare_env.backend == "mujoco":
    state = bare_env.reset(keys)

    def bare():
      s = bare_env.reset(keys)
      for _ in range(ran):
        s = bare_env.step(s, hold)
      return s.done

    t_bare = _best(bare, repeats)
  else:
    state = jax.jit(bare_env.reset)(keys)
    scan = jax.jit(lambda s: jax.lax.scan(lambda s, _: (bare_env.step(s, hold), None), s, None, length=ran)[0].done)
    t_bare = _best(lambda: scan(state), repeats)
  # the controller alone (network, normalisation, ensembling) on a frozen state
  cstate = controller.init(state)

  def queries(wts, cs):
    def body(cs, t):  # a state that changes each step, so no query is hoisted out of the loop
      s = state.replace(obs={**state.obs, "joint_pos": state.obs["joint_pos"] + 1e-3 * t})
      _, cs, _ = controller.act(wts, cs, s, t)
      return cs, None
    return jax.lax.scan(body, cs, jnp.arange(ran))[0]

  policy_only = jax.jit(queries)
  # the engine with a controller that holds the pose: its bookkeeping, with the bare run's physics
  hold_controller = Controller(lambda s: (), lambda wts, cs, s, t: (hold, cs, {}), name="hold")
  t_hold = _best(lambda: evaluate(benv, hold_controller, keys).success, repeats)
  t_only = _best(lambda: policy_only(controller.weights, cstate), repeats)
  return dict(task=task, backend=benv.backend, preset=preset, policy=policy, batch=batch, steps=ran,
              images=m.use_images, bare_control_steps_per_s=round(batch * ran / t_bare, 1),
              policy_control_steps_per_s=round(batch * ran / t_policy, 1),
              policy_over_bare_time=round(t_policy / t_bare, 2),
              ms_per_step=dict(bare_env=round(1e3 * t_bare / ran, 2), engine=round(1e3 * t_policy / ran, 2),
                               controller_alone=round(1e3 * t_only / ran, 2),
                               engine_holding_pose=round(1e3 * t_hold / ran, 2)))


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--task", default="jujube_pick")
  p.add_argument("--presets", default="quick", help="comma-separated: quick (state), budget, paper (images)")
  p.add_argument("--policies", default="act,skillplug")
  p.add_argument("--batches", default="16,64")
  p.add_argument("--steps", type=int, default=40, help="control steps per timed episode batch")
  p.add_argument("--repeats", type=int, default=2)
  p.add_argument("--backend", default="auto", choices=envs.BACKENDS)
  p.add_argument("--out", default="results/bench_eval.json")
  args = p.parse_args(argv)
  envs.quiet_warp()
  backend = envs.resolve_backend(args.backend)  # the command's edge: "auto" resolved once
  rows = []
  for preset in args.presets.split(","):
    for b in [int(v) for v in args.batches.split(",") if v]:
      for policy in args.policies.split(","):
        rows.append(bench(args.task, preset, policy, b, args.steps, args.repeats, backend))
        print(json.dumps(rows[-1]), flush=True)
  out = dict(device=str(jax.devices()[0]), platform=jax.devices()[0].platform,
             cpu_count=os.cpu_count(), results=rows)
  write_json_atomic(args.out, out)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()

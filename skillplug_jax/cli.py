"""The `skillplug` command."""

from __future__ import annotations

import argparse
import sys
import time


def cmd_experts(args) -> int:
  import jax
  import numpy as np
  from tqdm import tqdm

  import envs
  from envs import rollout

  names = [n for part in args.taskset.split(",") for n in envs.taskset(part)]
  backend = args.backend  # resolved by `main`
  from envs.libero import suites as libero_suites
  if any(libero_suites.is_libero(n) for n in names):
    return _libero_experts(args, names, backend)
  rows = []
  bar = tqdm(names, desc="experts", unit="task", file=sys.stderr)
  for name in bar:
    bar.set_postfix_str(name)
    env = envs.make(name, num_envs=min(args.batch, args.episodes), backend=backend)
    results, t0 = [], time.time()
    for start in range(0, args.episodes, env.num_envs):
      keys = rollout.reset_keys(args.seed, env.num_envs, offset=start)
      results.append(rollout.run_episodes(env, rollout.expert_controller(env), keys))
    succ = np.concatenate([r.success for r in results])[:args.episodes]
    first = np.concatenate([r.first_success_step for r in results])[:args.episodes]
    nan = np.concatenate([r.nan for r in results])[:args.episodes]
    overflow = np.concatenate([r.overflow for r in results])[:args.episodes]
    dt = env.env.config.control_dt
    rows.append(dict(
        task=name, abbr=env.env.abbr, episodes=int(len(succ)), success_rate=float(succ.mean()),
        mean_steps=float(first[succ].mean()) if succ.any() else None,
        mean_seconds=float(first[succ].mean() * dt) if succ.any() else None,
        time_limit_s=env.env.time_limit_s, nan_episodes=int(nan.sum()),
        solver_limit_episodes=envs.env.solver_limit_counts(overflow),
        wall_s=round(time.time() - t0, 1)))
  print(f"\nScripted experts, {args.episodes} episodes per task (seed {args.seed}, "
        f"backend {backend}, {jax.devices()[0].platform}):\n")
  print("| task | abbr | success | steps to success (steps / s) | limit (s) | NaN | solver / line-search limit | wall (s) |")
  print("|---|---|---|---|---|---|---|---|")
  for r in rows:
    length = "-" if r["mean_steps"] is None else f"{r['mean_steps']:.1f} / {r['mean_seconds']:.2f}"
    lim = r["solver_limit_episodes"]
    print(f"| {r['task']} | {r['abbr']} | {100 * r['success_rate']:.1f}% | {length} | "
          f"{r['time_limit_s']:.0f} | {r['nan_episodes']} | {lim['solver_iterations']} / "
          f"{lim['linesearch_iterations']} | {r['wall_s']} |")
  print("\nSteps to success: control steps to the first step of the 0.5 s the success held. The solver "
        "column counts episodes in which the constraint solver (or, on MuJoCo Warp, its line search) "
        "stopped at its iteration limit at least once (Warp's per-step warning is silenced; the C "
        "engine is sampled at the last substep of each control step).")
  if args.json:
    payload = dict(taskset=args.taskset, episodes=args.episodes, seed=args.seed, backend=backend,
                   device=str(jax.devices()[0]), tasks=rows)
    from skillplug_jax.atomic_json import write_json_atomic
    write_json_atomic(args.json, payload)
    print(f"\nwrote {args.json}")
  return 0


def _libero_experts(args, names: list[str], backend: str) -> int:
  """The LIBERO experts on the benchmark's init states (trial i = init state i, as LIBERO evaluates)."""
  from tqdm import tqdm

  from envs.libero import expert, suites
  if backend != "mujoco" or not all(suites.is_libero(n) for n in names):
    raise SystemExit("skillplug experts: LIBERO tasks run on MuJoCo's C engine (--backend mujoco), "
                     "and not in one taskset with DISCOVERSE tasks")
  trials = min(args.episodes, suites.INIT_STATES_PER_TASK)
  rows = []
  bar = tqdm(names, desc="experts", unit="task", file=sys.stderr)
  for name in bar:
    bar.set_postfix_str(name)
    task, t0 = suites.parse(name), time.time()
    try:
      row = expert.run(task.suite, task.index, trials)
    except NotImplementedError as e:
      row = {"suite": task.suite, "task": task.index, "name": task.name, "trials": trials, "not_scripted": str(e)}
    rows.append({"id": name, **row, "wall_s": round(time.time() - t0, 1)})
  print(f"\nScripted LIBERO experts on the benchmark's first {trials} init states per task (backend {backend}):\n")
  print("| task | LIBERO task | success | LIBERO's success | median steps to LIBERO's success | limit | wall (s) |")
  print("|---|---|---|---|---|---|---|")
  for r in rows:
    if "not_scripted" in r:
      print(f"| {r['id']} | {r['name']} | not scripted | | | | |")
      continue
    steps = "-" if r["median_steps"] is None else f"{r['median_steps']:.0f}"
    print(f"| {r['id']} | {r['name']} | {100 * r['success']:.0f}% | {100 * r['libero_success']:.0f}% | {steps} | "
          f"{r['time_limit']} | {r['wall_s']} |")
  print("\nSuccess: the goal holds with the gripper open and the hand withdrawn, and still holds "
        f"{expert.HOLD_STEPS} steps later. LIBERO's success: its predicate at any step within the limit.")
  if args.json:
    from skillplug_jax.atomic_json import write_json_atomic
    write_json_atomic(args.json, dict(taskset=args.taskset, trials=trials, backend=backend, tasks=rows))
    print(f"\nwrote {args.json}")
  return 0


def cmd_demos(args) -> int:
  from skillplug_jax.data import demos, loader

  cfg = demos.DemoConfig(taskset=args.taskset, demos=args.demos, images=not args.state_only,
                         image_size=(args.image_size, args.image_size), seed=args.seed,
                         batch=args.batch, backend=args.backend)
  t0 = time.time()
  path = demos.make_demos(cfg, out=args.out)
  d = loader.load_demonstrations(path, images=cfg.images)
  print(f"\n{path}: {d.num_episodes} episodes, {int(d.length.sum())} steps, "
        f"{_dir_mb(path):.1f} MB on disk ({time.time() - t0:.0f} s)")
  print("| task | episodes | mean length (steps) |")
  print("|---|---|---|")
  for i, task in enumerate(d.tasks):
    sel = d.task_id == i
    print(f"| {task} | {int(sel.sum())} | {d.length[sel].mean():.1f} |")
  return 0


def start_distributed(args) -> None:
  """`pretrain --distributed`: jax.distributed.initialize(), before anything runs on a device (the
  backend's resolution included, `main`)."""
  import jax

  explicit = {"--coordinator": args.coordinator or None, "--num-processes": args.num_processes,
              "--process-id": args.process_id}
  if not args.distributed and any(v is not None for v in explicit.values()):
    raise ValueError(f"{', '.join(k for k, v in explicit.items() if v is not None)} need --distributed")
  if args.distributed:
    # Several processes (hosts) train one run: coordinator, process count and this process's
    # id as given, the rest from the cluster's environment (SLURM, Open MPI, TPU). On CPU the
    # cross-process all-reduce is jax's default CPU collectives implementation (gloo over TCP).
    jax.distributed.initialize(coordinator_address=explicit["--coordinator"],
                               num_processes=args.num_processes, process_id=args.process_id)


def cmd_pretrain(args) -> int:
  import jax

  from skillplug_jax import experiment
  from skillplug_jax.train import config, loop

  exp = experiment.get(args.config)
  cfg = config.override(exp.train_config(args.policy, seed=0),
                        [f"taskset={args.taskset}", f"seed={args.seed}", f"backend={args.backend}"]
                        + list(args.set or []))
  if args.workdir:
    cfg = config.override(cfg, [f"workdir={args.workdir}"])
  if args.distributed:  # the dataset
    from skillplug_jax.data import demos as demo_data
    dcfg = loop.dataset_config(cfg)
    if not demo_data.dataset_path(dcfg, cfg.data_dir).exists():  # not one writer per process: made beforehand
      images = f"--image-size {dcfg.image_size[0]}" if dcfg.images else "--state-only"
      raise ValueError(f"{demo_data.dataset_path(dcfg, cfg.data_dir)} is missing: with --distributed, generate "
                       f"it first, on the filesystem every host reads: skillplug demos --taskset {dcfg.taskset} "
                       f"--demos {dcfg.demos} {images} --seed {dcfg.seed} --backend {dcfg.backend} "
                       f"--out {cfg.data_dir}")
  run = loop.train(cfg, progress=jax.process_index() == 0,  # one progress bar, from the first process
                   record=experiment.record(exp, args.policy, experiment.directory(args.config)))
  print(f"checkpoint: {run / 'checkpoints'} (config and normalisation statistics beside it in {run})")
  return 0


def cmd_eval(args) -> int:
  import envs
  from skillplug_jax.evaluate import protocol, report

  runs = _expand_seeds([r for part in args.runs for r in part.split(",") if r], args.seeds)
  tasks = [n for part in args.taskset.split(",") for n in envs.taskset(part)]
  video_dir = args.video_dir or (f"{args.out}_videos" if args.out else "videos")
  from envs.libero import suites as libero_suites
  if any(libero_suites.is_libero(t) for t in tasks):
    return _libero_eval(args, runs, tasks, video_dir)
  out = protocol.evaluate_runs(runs, tasks, args.trials, seed=args.seed, batch=args.batch,
                               query_every=args.query_every, videos=args.videos, video_dir=video_dir,
                               backend=args.backend, appearance=args.appearance,
                               routing_smoothing=args.routing_smoothing)
  shift = ", appearance shifted" if args.appearance != "default" else ""
  shift += f", routing smoothed {args.routing_smoothing}" if args.routing_smoothing else ""
  print(report.write(out, f"{args.trials} paired trials per task (seed {args.seed}{shift})", args.out))
  if args.videos:
    print(f"videos of the first {args.videos} trials per task: {video_dir}/<run>/<task>_trialNN.gif")
  return 0


def _libero_eval(args, runs: list[str], tasks: list[str], video_dir: str) -> int:
  """`skillplug eval` on LIBERO tasks: the benchmark's init states as the paired trials."""
  from envs.libero import suites
  from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
  from skillplug_jax.evaluate import libero

  if not all(suites.is_libero(t) for t in tasks):
    raise SystemExit("skillplug eval: LIBERO and DISCOVERSE tasks are evaluated separately")
  if args.trials > suites.INIT_STATES_PER_TASK:
    raise SystemExit(f"skillplug eval: LIBERO has {suites.INIT_STATES_PER_TASK} init states per task; "
                     f"--trials {args.trials} is more")
  out = libero.evaluate_runs(runs, tasks, args.trials, args.videos, video_dir)
  text = libero.report(out)
  print("\n" + text)
  if args.out:
    write_json_atomic(f"{args.out}.json", out)
    write_text_atomic(f"{args.out}.md", text + "\n")
    print(f"wrote {args.out}.json, {args.out}.md")
  if args.videos:
    print(f"videos of the first {args.videos} trials per task: {video_dir}/<run>/<suite>_<index>_trialNN.gif")
  return 0


def _expand_seeds(runs: list[str], seeds: str) -> list[str]:
  """`--ckpt results/runs/x_seed{seed} --seeds 0,1,2`: one run directory per training seed."""
  if not seeds:
    bad = [r for r in runs if "{seed}" in r]
    if bad:
      raise ValueError(f"{bad[0]} has a {{seed}} placeholder: give --seeds")
    return runs
  values = [v for v in seeds.split(",") if v]
  if not all(v.isdigit() for v in values):
    raise ValueError(f"--seeds must be comma-separated integers, got {seeds!r}")
  if not all("{seed}" in r for r in runs):
    raise ValueError("--seeds needs run directories with a {seed} placeholder, e.g. results/runs/x_seed{seed}")
  return [r.replace("{seed}", v) for r in runs for v in values]


def cmd_fewshot(args) -> int:
  from skillplug_jax import fewshot
  from skillplug_jax.evaluate import report

  runs = [r for part in args.runs for r in part.split(",") if r]
  out = fewshot.adapt_and_evaluate(runs, args.taskset, args.demos, args.trials, args.seed, args.batch,
                                   steps=args.steps, backend=args.backend,
                                   marginal_terms=False if args.no_marginal_terms else None,
                                   trainable=args.trainable.split(",") if args.trainable else None,
                                   per=args.per)
  print(report.write(out, f"few-shot, {args.demos} demos per task, {args.trials} paired trials per task",
                     args.out))
  return 0


def _dir_mb(path) -> float:
  return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def _backend_flag(parser, what: str = "physics backend") -> None:
  from envs.names import BACKENDS
  parser.add_argument("--backend", default="auto", choices=BACKENDS,
                      help=f"{what}: mujoco (MuJoCo's C engine, fastest on a CPU), mjx-warp (MJX on "
                           "MuJoCo Warp, for GPUs), auto (mjx-warp when JAX sees a GPU, else mujoco)")


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="skillplug", description=__doc__)
  sub = p.add_subparsers(dest="command", required=True)
  e = sub.add_parser("experts", help="run the scripted experts and print their success table",
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  e.add_argument("--taskset", required=True, help="discoverse7, discoverse_fewshot4, a LIBERO suite (libero_object, "
                 "...), or task names (comma-separated; LIBERO's: libero_object:3)")
  e.add_argument("--episodes", type=int, default=100, help="seeded episodes per task (LIBERO: the benchmark's "
                 "init states, at most 50)")
  e.add_argument("--batch", type=int, default=100, help="environments simulated at once")
  e.add_argument("--seed", type=int, default=0)
  _backend_flag(e)
  e.add_argument("--json", default=None, help="also write the table as JSON here")
  e.set_defaults(fn=cmd_experts)

  d = sub.add_parser("demos", help="generate expert demonstrations as an RLDS dataset (tfds)",
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  d.add_argument("--taskset", required=True, help="discoverse7, discoverse_fewshot4, a LIBERO suite (libero_object, "
                 "...: drawn starts, not the benchmark's init states), or task names (comma-separated)")
  d.add_argument("--demos", type=int, default=300, help="successful episodes kept per task")
  d.add_argument("--out", default="results/datasets", help="datasets directory")
  d.add_argument("--state-only", action="store_true", help="no camera images (state-based policies)")
  d.add_argument("--image-size", type=int, default=64, help="square camera images, pixels")
  d.add_argument("--seed", type=int, default=0, help="reset seed of episode 0 (episode i uses fold_in(seed, i); "
                 "LIBERO: the seed of its placement samplers' draws)")
  d.add_argument("--batch", type=int, default=64, help="environments simulated at once")
  _backend_flag(d)
  d.set_defaults(fn=cmd_demos)

  t = sub.add_parser("pretrain", help="train a multi-task policy (generates its demos when missing)",
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  t.add_argument("--taskset", default="discoverse7")
  t.add_argument("--policy", default="skillplug", choices=("skillplug", "act"))
  t.add_argument("--config", "--preset", dest="config", default="quick", metavar="NAME",
                 help="experiments/configs/NAME.py, or a path to a config file: quick (CPU minutes, state "
                      "only), cpu (the CPU-scale preset), budget (~10 min of one GPU), paper (the paper's "
                      "protocol), or another config; the run records it (its few-shot protocol and settings)")
  t.add_argument("--seed", type=int, default=0, help="training seed (initialisation, batches, dropout)")
  t.add_argument("--set", action="append", metavar="KEY=VALUE",
                 help="override a config field, e.g. --set lr=3e-4 --set model.hidden=128 --set loss.sd=0.5")
  t.add_argument("--workdir", default="", help="run directory (default results/runs/<taskset>_<policy>_<preset>_seed<seed>)")
  _backend_flag(t, "physics of the demonstrations generated when missing (recorded in the run's config)")
  t.add_argument("--distributed", action="store_true",
                 help="train with several processes (hosts) on one run directory: jax.distributed.initialize(), "
                      "settings from the cluster's environment (SLURM, Open MPI) unless given below")
  t.add_argument("--coordinator", default="", metavar="HOST:PORT",
                 help="with --distributed: the address of process 0, which every process connects to")
  t.add_argument("--num-processes", type=int, default=None, metavar="N", help="with --distributed: processes in all")
  t.add_argument("--process-id", type=int, default=None, metavar="I", help="with --distributed: this process's id, 0..N-1")
  t.set_defaults(fn=cmd_pretrain)

  v = sub.add_parser("eval", help="closed-loop success rates of trained policies (paired trials)",
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  v.add_argument("--runs", "--ckpt", dest="runs", nargs="+", required=True,
                 help="run directories (one per training seed; ACT and SkillPlug runs may be mixed); "
                      "with --seeds, '{seed}' in a path is replaced by each seed")
  v.add_argument("--seeds", default="", help="training seeds for '{seed}' in --runs, e.g. 0,1,2")
  v.add_argument("--taskset", default="discoverse7")
  v.add_argument("--trials", type=int, default=50, help="seeded episodes per task")
  v.add_argument("--seed", type=int, default=1000, help="trial i starts from reset_keys(seed)[i] for every policy")
  v.add_argument("--batch", type=int, default=50, help="environments simulated at once")
  v.add_argument("--query-every", type=int, default=1,
                 help="1: query every step with temporal ensembling; n > 1: open-loop chunks of n steps")
  v.add_argument("--out", default="", help="write OUT.json, OUT.md, OUT.csv, OUT.queries.csv, OUT.queries_paired.csv")
  v.add_argument("--videos", type=int, default=0, help="GIFs (side camera) of the first N trials per task")
  v.add_argument("--video-dir", default="", help="where the GIFs go (default OUT_videos, or ./videos)")
  _backend_flag(v, "physics the policies are evaluated on")
  v.add_argument("--appearance", default="default", choices=("default", "shifted"),
                 help="shifted: each trial's cameras see other table, object and light colours, drawn from "
                      "(seed, trial); the physics and trials are the default's (ours, docs/evaluation.md)")
  v.add_argument("--routing-smoothing", type=float, default=0.0, metavar="S",
                 help="ACT+SkillPlug only: decode each query with r_t = S r_(t-1) + (1 - S) router(o_t), "
                      "an exponential average of the router's weights over queries (ours; 0: its own)")
  v.set_defaults(fn=cmd_eval)

  f = sub.add_parser("fewshot", help="adapt multi-task runs to unseen tasks from a few demos, then evaluate",
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  f.add_argument("--from", dest="runs", nargs="+", required=True,
                 help="multi-task run directories (one per training seed)")
  f.add_argument("--taskset", default="discoverse_fewshot4")
  f.add_argument("--demos", type=int, default=10, help="demonstrations per unseen task")
  f.add_argument("--steps", type=int, default=None,
                 help="fine-tuning steps (default: the few-shot steps the source run recorded of its config, "
                      "e.g. quick 500; 0 trains the source's epochs)")
  f.add_argument("--no-marginal-terms", action="store_true",
                 help="fine-tune without the source's loss.usage (a term on the batch's "
                      "mean routing; ours, issue 27); fine-tunes go to RUN_fewshot_no_marginal_terms/")
  f.add_argument("--trainable", default="",
                 help="parameter groups to fine-tune, comma-separated, for either policy (default: those the "
                      "source run recorded), e.g. action_head,router,interactor (the groups: docs/training.md); "
                      "other than the recorded ones, fine-tunes go to RUN_fewshot_train-<groups>/")
  f.add_argument("--per", choices=("task", "taskset"), default=None,
                 help="one fine-tune per task of the taskset, or per comma-separated part of it (a LIBERO suite: "
                      "the paper's LIBERO protocol); default: what the source run recorded")
  f.add_argument("--trials", type=int, default=50)
  f.add_argument("--seed", type=int, default=1000)
  f.add_argument("--batch", type=int, default=50)
  f.add_argument("--out", default="", help="write OUT.json, OUT.md, OUT.csv, OUT.queries.csv, OUT.queries_paired.csv")
  _backend_flag(f, "physics of evaluation (the few-shot demos follow the source run's backend)")
  f.set_defaults(fn=cmd_fewshot)
  return p


def main(argv=None) -> int:
  if argv is None:  # the command line, not a call: glibc's allocator setting as make exports it
    from skillplug_jax import startup
    startup.prepare_process()
  args = build_parser().parse_args(argv)
  for flag in ("episodes", "demos", "batch", "trials"):
    if getattr(args, flag, 1) < 1:
      raise SystemExit(f"skillplug: --{flag} must be >= 1")
  import envs
  envs.quiet_warp()
  from skillplug_jax.train.preemption import Stopped
  try:
    if args.command == "pretrain":
      start_distributed(args)  # before the backend is resolved: that asks JAX for its devices
    if hasattr(args, "backend"):  # "auto" is resolved here, once; the commands pass it down
      args.backend = envs.resolve_backend(args.backend)
    return args.fn(args)
  except Stopped as e:  # SIGTERM/SIGINT during training (`Preempted`): its step is checkpointed
    print(f"skillplug: {e}", file=sys.stderr)
    return e.exit_code
  except ValueError as e:  # bad names, shapes, datasets, checkpoints: one clear line
    print(f"skillplug: error: {e}", file=sys.stderr)
    return 2
  except RuntimeError as e:  # non-finite loss, experts that cannot succeed
    print(f"skillplug: error: {e}", file=sys.stderr)
    return 1


if __name__ == "__main__":
  sys.exit(main())

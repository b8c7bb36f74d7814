"""What the skills do, and whether the plug is more than ACT: probes of a pipeline's ACT+SkillPlug runs.

    python -m experiments.skill_probes --config cpu --out results/paper_cpu --publish docs/results/paper_cpu

For every training seed of the config's ACT+SkillPlug runs (found where
`experiments.pipeline` put them under --out; for a config with variants,
every variant's, e.g. `--config k_sweep --geometry-only` for the skills'
similarity at each K):

1. closed loop on the pretraining tasks with the router's weights replaced:
   `router` (its own), `uniform` (1/K each: what a router that learned
   nothing would give) and `skill<k>` (one-hot: each skill alone). If
   uniform and every one-hot match the router, the skills are
   interchangeable and the library does nothing ACT could not;
2. the skills' geometry, per task, on demonstration states: cosine
   similarity of the skill embeddings s_k and of the interactor outputs u_k
   (token-averaged), how far the u_k spread around their mean, how much the
   fused feature h~ differs from the encoder's h, and linear CKA between
   h~ and the same seed's ACT encoder output (1: the plug's feature is
   ACT's feature up to a rotation and scale); and whether the router's
   choice follows the manipulation phase mined from each demonstration
   (data/segments.py tabletop_phases): NMI, and the skills each phase picks.

Evaluations are cached beside each run (`<run>/eval/probe_<mode>_*.json`),
so a killed probe resumes. Writes OUT/skill_probes.{json,md}.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import envs
from experiments import pipeline
from skillplug_jax import diagnostics, experiment
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.data import loader as data_loader
from skillplug_jax.data import segments
from skillplug_jax.evaluate import tables, trials
from skillplug_jax.evaluate.tables import mean_se
from skillplug_jax.evaluate.policy_controller import load_controller
from skillplug_jax.evaluate.routing import nmi
from skillplug_jax.experiment import Experiment
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import loop, run_files


def modes(k: int, pairs: bool = False, drops: bool = False) -> dict[str, tuple[float, ...] | None]:
  """Routing modes: the router's own, uniform, each skill alone; with `pairs` each pair of skills
  half and half (`mix<a><b>`: the paper's mixed-skill rollouts); with `drops` uniform over all
  skills but one (`drop<k>`: what the policy loses when skill k is removed)."""
  out = {"router": None, "uniform": (1.0 / k,) * k}
  out.update({f"skill{i}": tuple(float(i == j) for j in range(k)) for i in range(k)})
  if pairs:
    out.update({f"mix{a}{b}": tuple(0.5 * (j in (a, b)) for j in range(k)) for a in range(k) for b in range(a + 1, k)})
  if drops and k > 1:
    out.update({f"drop{i}": tuple(0.0 if j == i else 1.0 / (k - 1) for j in range(k)) for i in range(k)})
  return out


def select(all_modes: dict, wanted: str) -> dict:
  """The modes named in `wanted` (comma-separated; empty: all), in their order in `all_modes`."""
  if not wanted:
    return all_modes
  names = wanted.split(",")
  unknown = [n for n in names if n not in all_modes]
  if unknown:
    raise ValueError(f"unknown routing mode(s) {unknown}; this run has: {', '.join(all_modes)}")
  return {m: w for m, w in all_modes.items() if m in names}


def closed_loop(run: Path, exp: Experiment, tasks, k: int, videos: int = 0,
                video_dir: Path | None = None, chosen: dict | None = None) -> dict:
  """{mode: {task: success rate}} for every routing mode (cached per mode).

  videos > 0: GIFs of the side camera of each task's first `videos` trials
  in every mode, video_dir/<mode>/<task>_trialNN.gif (written when a mode is
  evaluated, not when it is read back)."""
  out = {}
  own = run / "eval" / f"{exp.train.taskset}_trials{exp.trials}_seed{exp.eval_seed}.json"  # the pipeline's
  for mode, weights in (modes(k) if chosen is None else chosen).items():
    path = run / "eval" / f"probe_{mode}_trials{exp.trials}_seed{exp.eval_seed}.json"
    if mode == "router" and own.exists() and not videos:
      out[mode] = {r["task"]: dict(success_rate=r["success_rate"], trial_success=r["trial_success"])
                   for r in json.loads(own.read_text())["results"]}
      continue
    if not path.exists():
      controller, cfg = load_controller(run, routing=weights)
      res = {}
      for task in tasks:  # our tabletop's trials or LIBERO's (the benchmark's init states)
        r = trials.evaluate_task(task, controller, cfg, exp.trials, exp.eval_seed, exp.eval_batch,
                                 backend=envs.resolve_backend(exp.train.backend), videos=videos,
                                 video_dir=None if video_dir is None else video_dir / mode)
        res[task] = dict(success_rate=r["success_rate"], trial_success=r["trial_success"])
      write_json_atomic(path, res)
    out[mode] = json.loads(path.read_text())
  return out


def _features(module: Policy, obs):
  """The inference path's plug input (scene tokens, or decoder steps with plug.site='decoder'),
  interactor outputs, routing, fused feature and skill embeddings."""
  f = module.features(obs)
  return f["plug_input"], f["skill_tokens"], f["routing"], f["fused"], module.plug.skills()


def _cos(a, b):
  a = a / np.linalg.norm(a, axis=-1, keepdims=True)
  b = b / np.linalg.norm(b, axis=-1, keepdims=True)
  return (a * b).sum(-1)


def linear_cka(x: np.ndarray, y: np.ndarray) -> float:
  """Linear CKA of two feature sets [n, d1], [n, d2] (Kornblith et al. 2019): 1 when one is
  a rotation and scaling of the other, whatever their bases."""
  x = x - x.mean(0)
  y = y - y.mean(0)
  hsic = np.linalg.norm(x.T @ y) ** 2
  return float(hsic / (np.linalg.norm(x.T @ x) * np.linalg.norm(y.T @ y)))


def demo_states(run: Path, tasks, per_episode: int = 4) -> dict[str, dict]:
  """Observations of each task's demonstrations (`per_episode` evenly spaced timesteps of each)."""
  cfg = run_files.read_config(run)
  data = loop.load_data(cfg, generate=False, progress=False)
  data = dataclasses.replace(data, stats=run_files.read_stats(run))
  data, instructions = loop.instruction_ids(cfg, data)  # a policy that reads its task's instruction
  ld = data_loader.ChunkLoader(data, 1, chunk=cfg.model.chunk, images=cfg.model.use_images,
                               normalize_object_state=cfg.model.normalize_object_state, instructions=instructions)
  # each state's manipulation phase mined from its demonstration (data/segments.py), whatever the
  # run trained on: does the routing follow the phases?
  phases = loop.skill_labels(dataclasses.replace(cfg, skill_labels="tabletop_phases"), data)
  out = {}
  for i, task in enumerate(data.tasks):
    if task not in tasks:
      continue
    eps = np.flatnonzero(data.task_id == i)
    ep = np.repeat(eps, per_episode)
    frac = np.tile((np.arange(per_episode) + 0.5) / per_episode, len(eps))
    t = np.floor(frac * data.length[ep]).astype(np.int64)
    b = ld.gather(ep, t)
    read = set(cfg.model.proprio) | {"joint_pos", "object_state", "instruction"}  # what the policy reads
    out[task] = {k: v for k, v in b.items() if k in read or k.endswith("_rgb")}
    out[task]["mined_phase"] = phases[data.start[ep] + t]
  return out


def geometry(run: Path, act_run: Path | None, tasks) -> dict:
  """Per task: skill and interactor-output similarity, spread, and CKA against ACT's encoder."""
  cfg, params, _ = loop.load_params(run)
  policy = Policy(cfg.model)
  feats = jax.jit(lambda p, o: policy.apply({"params": p}, o, method=_features))
  act = None
  if act_run is not None:
    acfg, aparams, _ = loop.load_params(act_run)
    apolicy = Policy(acfg.model)
    act = (jax.jit(lambda p, o: apolicy.apply({"params": p}, o, method=Policy.encode)[0]), aparams)
  states = demo_states(run, tasks)
  if not states:
    raise ValueError(f"{run}: its demonstrations hold none of the tasks {', '.join(tasks)}")
  out = {}
  skills = None
  chosen, phase = [], []
  for task, obs in states.items():
    phase.append(obs.pop("mined_phase"))
    h, u, r, fused, skills = map(np.asarray, feats(params, obs))
    chosen.append(r.argmax(-1))
    um = u.mean(axis=2)  # [B, K, D] token-averaged u_k
    k = um.shape[1]
    sim = np.array([[_cos(um[:, a], um[:, b]).mean() for b in range(k)] for a in range(k)])
    centre = um.mean(axis=1, keepdims=True)
    spread = float((np.linalg.norm(um - centre, axis=-1) / np.linalg.norm(centre, axis=-1)).mean())
    row = dict(interactor_cosine=sim.round(4).tolist(),
               interactor_offdiag_cosine=float(sim[~np.eye(k, dtype=bool)].mean()),
               interactor_spread=spread,
               fused_vs_encoder_cosine=float(_cos(fused.reshape(-1, fused.shape[-1]), h.reshape(-1, h.shape[-1])).mean()),
               fused_vs_mean_u_cosine=float(_cos(fused.reshape(-1, fused.shape[-1]),
                                                 u.mean(axis=1).reshape(-1, fused.shape[-1])).mean()),
               router_mean=r.mean(0).tolist(), states=int(h.shape[0]),
               diagnostics=diagnostics.as_json(dict(diagnostics.skill_geometry(u, h, r),
                                                    routing=diagnostics.routing_stats(r))))
    if act is not None:
      ha = np.asarray(act[0](act[1], obs))
      row["cka_fused_vs_act"] = linear_cka(fused.reshape(fused.shape[0], -1), ha.reshape(ha.shape[0], -1))
      row["cka_encoder_vs_act"] = linear_cka(h.reshape(h.shape[0], -1), ha.reshape(ha.shape[0], -1))
    out[task] = row
  emb = np.asarray(skills)
  k = emb.shape[0]
  esim = np.array([[_cos(emb[a], emb[b]) for b in range(k)] for a in range(k)])
  chosen, phase = np.concatenate(chosen), np.concatenate(phase)
  return dict(tasks=out, skill_cosine=esim.round(4).tolist(),
              skill_offdiag_cosine=float(esim[~np.eye(k, dtype=bool)].mean()),
              phase_skill_nmi=nmi(chosen, phase),
              phase_skill_counts=[np.bincount(chosen[phase == q], minlength=k).tolist()
                                  for q in range(len(segments.PHASES))])


def report(result: dict) -> str:
  runs = list(result["seeds"])  # "0", "1", ... or, for a config with variants, "<variant>/seed<S>"
  looped = [s for s in runs if "closed_loop" in result["seeds"][s]]
  # one closed-loop table per training taskset (runs of libero_cpu's arms are on different suites)
  by_tasks: dict[tuple, list[str]] = {}
  for s in looped:
    by_tasks.setdefault(tuple(result["seeds"][s].get("tasks", result["tasks"])), []).append(s)
  lines = []
  for tasks, group in by_tasks.items():
    lines += ([""] if lines else []) + closed_loop_report(result, group, tasks, [tables.abbr(t) for t in tasks])
  lines += ["", "Skill geometry on demonstration states (per run, mean over the tasks; per task in the JSON); "
            "phase NMI: the router's choice (argmax) against the manipulation phase mined from the "
            "demonstration (data/segments.py), all tasks pooled:", "",
            "| run | K | skill cos (off-diag) | u_k cos (off-diag) | u_k spread | cos(h~, h) | cos(h~, mean u) | CKA(h~, ACT h) | CKA(h, ACT h) | phase NMI |",
            "|---|---|---|---|---|---|---|---|---|---|"]
  for s in runs:
    g = result["seeds"][s]["geometry"]
    m = lambda key: float(np.mean([g["tasks"][t][key] for t in g["tasks"]])) if all(key in g["tasks"][t] for t in g["tasks"]) else float("nan")  # noqa: E731
    lines.append(f"| {s} | {len(g['skill_cosine'])} | {g['skill_offdiag_cosine']:.3f} | {m('interactor_offdiag_cosine'):.3f} | "
                 f"{m('interactor_spread'):.3f} | {m('fused_vs_encoder_cosine'):.3f} | {m('fused_vs_mean_u_cosine'):.3f} | "
                 f"{m('cka_fused_vs_act'):.3f} | {m('cka_encoder_vs_act'):.3f} | "
                 f"{g.get('phase_skill_nmi', float('nan')):.3f} |")
  return "\n".join(lines)


def closed_loop_report(result: dict, seeds: list[str], tasks, abbr) -> list[str]:
  """Success per routing mode, mean ± SE over the runs that were rolled out."""
  lines = [f"Closed-loop success (%) of ACT+SkillPlug with the router's weights replaced; mean ± SE over "
           f"seed(s) {', '.join(seeds)}; {result['trials']} paired trials per task:", "",
           "| routing | " + " | ".join(abbr) + " | Avg. |", "|---|" + "---|" * (len(abbr) + 1)]
  def cell(v):
    m, se = mean_se(v)
    return f"{m:.1f}" if se is None else f"{m:.1f}±{se:.1f}"

  def rate(s, mode, t):
    return 100 * result["seeds"][s]["closed_loop"][mode][t]["success_rate"]

  for mode in result["modes"]:
    per = [[rate(s, mode, t) for s in seeds] for t in tasks]
    avg = [float(np.mean([per[i][j] for i in range(len(tasks))])) for j in range(len(seeds))]
    lines.append(f"| {mode} | " + " | ".join(cell(v) for v in per) + f" | {cell(avg)} |")
  # skill k of one seed is not skill k of another: per seed, its best and its mean single skill
  singles = [m for m in result["modes"] if m.startswith("skill")]
  if not singles:
    return lines
  for name, pick in (("best single skill (per seed)", max), ("mean single skill (per seed)", np.mean)):
    per_seed = {s: {t: [rate(s, m, t) for m in singles] for t in tasks} for s in seeds}
    best = {s: max(singles, key=lambda m: np.mean([rate(s, m, t) for t in tasks])) for s in seeds}
    if pick is max:
      per = [[rate(s, best[s], t) for s in seeds] for t in tasks]
    else:
      per = [[float(np.mean(per_seed[s][t])) for s in seeds] for t in tasks]
    avg = [float(np.mean([per[i][j] for i in range(len(tasks))])) for j in range(len(seeds))]
    lines.append(f"| {name} | " + " | ".join(cell(v) for v in per) + f" | {cell(avg)} |")
  return lines


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--config", default="cpu")
  p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
  p.add_argument("--out", default="", help="the pipeline's output folder (default results/<config>)")
  p.add_argument("--publish", default="", help="also copy skill_probes.{json,md} here")
  p.add_argument("--variants", default="", metavar="A,B", help="of a config with variants, only these")
  p.add_argument("--pairs", action="store_true",
                 help="also roll out every pair of skills half and half (mix<a><b>: mixed-skill rollouts)")
  p.add_argument("--drops", action="store_true",
                 help="also roll out uniform routing over all skills but one (drop<k>: skill k removed)")
  p.add_argument("--modes", default="", metavar="A,B",
                 help="only these routing modes (router, uniform, skill<k>; mix<a><b> with --pairs, drop<k> with --drops)")
  p.add_argument("--geometry-only", action="store_true",
                 help="only the skills' geometry (seconds per run), no closed-loop rollouts")
  p.add_argument("--videos", type=int, default=0,
                 help="GIFs of each task's first N trials in every routing mode, for the first seed "
                      "(OUT/probe_videos/seed<S>/<mode>/<task>_trialNN.gif; only for modes not yet cached; "
                      "rendered offscreen: EGL or OSMesa, docs/tasks.md#images)")
  args = p.parse_args(argv)
  envs.quiet_warp()
  try:
    exp = experiment.only(experiment.get(args.config, args.set), args.variants, args.config)
    out = Path(args.out or f"results/{args.config}")
    by_arm = pipeline.arms(exp, out)
    # arms may train on different suites (libero_cpu): each run is probed on its own training tasks
    every = tuple(dict.fromkeys(t for _, arm, _ in by_arm for t in pipeline.tasks_of(arm.train.taskset)))
    result = dict(config=args.config, trials=exp.trials, eval_seed=exp.eval_seed, tasks=list(every), seeds={},
                  device=str(jax.devices()[0]))
    t0 = time.time()
    for variant, arm, arm_out in by_arm:
      tasks = pipeline.tasks_of(arm.train.taskset)
      for seed in arm.seeds:
        run = pipeline.pretrain_config(arm, "skillplug", seed, arm_out).run_dir
        act_run = pipeline.pretrain_config(arm, "act", seed, arm_out).run_dir
        if not (run / "config.json").exists():
          raise ValueError(f"{run} does not exist: run the pipeline first (python -m experiments.pipeline "
                           f"--config {args.config} --out {out})")
        k = run_files.read_config(run).model.plug.num_skills
        key = f"{variant.name}/seed{seed}" if variant.name else str(seed)
        entry = dict(run=str(run), variant=variant.name, label=variant.label or variant.name, tasks=list(tasks))
        if not args.geometry_only:
          chosen = select(modes(k, args.pairs, args.drops), args.modes)
          result["modes"] = list(chosen)
          print(f"[probes] {key}: closed loop with {len(chosen)} routings ...", file=sys.stderr, flush=True)
          entry["closed_loop"] = closed_loop(run, arm, tasks, k, videos=args.videos if not result["seeds"] else 0,
                                             video_dir=out / "probe_videos" / f"seed{seed}", chosen=chosen)
        entry["geometry"] = geometry(run, act_run if (act_run / "config.json").exists() else None, tasks)
        result["seeds"][key] = entry
    result["wall_s"] = round(time.time() - t0, 1)
  except (ValueError, RuntimeError) as e:
    print(f"skill_probes: error: {e}", file=sys.stderr)
    return 2 if isinstance(e, ValueError) else 1
  text = report(result)
  print(text)
  for dest in [out] + ([Path(args.publish)] if args.publish else []):
    write_json_atomic(dest / "skill_probes.json", result)
    write_text_atomic(dest / "skill_probes.md", text + "\n")
  print(f"wrote {out / 'skill_probes.md'} and .json")
  return 0


if __name__ == "__main__":
  sys.exit(main())

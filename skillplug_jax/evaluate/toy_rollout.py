"""The toy problem's closed loop (envs/toy_skills.py), its routing against the known primitives,
and the fixed-skill probe: how the pipeline evaluates a toy run (`experiments.pipeline.job`).

Closed loop: one jitted `lax.scan` over control steps of vmapped environments, the policy
queried every step, its first action run (`ToyProtocol.query`; ACT's temporal ensembling is an
option). Trial i of a call is the same start for every run (paired). `evaluated` writes
per-task results in the record format of `experiments.pipeline.evaluated` (success, trials,
row fields, routing diagnostics, the routing arrays beside them), so the pipeline's tables and
`experiments.publish` read the toy as any config, with the toy's extras as fields of each
result:
  stage_progress  the mean fraction of the task's stages done by the time limit (ranks arms
                  where success is rare)
  toy_routing     `evaluate.routing` statistics of the queries made while the task ran, and
                  `nmi` (argmax routing against the primitive the environment was executing),
                  nmi_stage, nmi_quadrant (the robot's quadrant of the table)
and per run (`run_extras`, on the seen tasks together): the same routing statistics with
nmi_task; the fixed-skill probe (routing one-hot on each skill k for the whole time limit:
what the robot does, ends within `probe_radius` of landmark A, B or C, else toggles the
gripper, else nothing; and uniform routing, which a router that learned nothing gives); and
zero-shot success and stage progress on the unseen tasks.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from envs import toy_skills as toy
from skillplug_jax import experiment
from skillplug_jax.atomic_json import write_json_atomic
from skillplug_jax.evaluate import groups, protocol, routing
from skillplug_jax.evaluate.policy_controller import temporal_ensemble
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import loop, run_files
from skillplug_jax.train import toy as toy_train


@dataclasses.dataclass(frozen=True)
class ToyProtocol:
  """What the toy's evaluation does besides the experiment's trials and eval_seed."""
  env: toy.ToySkillsConfig = toy_train.ENV
  # 'first': query every step, run the chunk's first action; 'ensemble': ACT's temporal ensembling
  # (it mixes stale absolute targets: ACT 43% against 54% with 'first' at radius 0.05).
  query: str = "first"
  probe_trials: int = 10  # per seen task, per fixed routing
  probe_radius: float = 0.15  # "ends at landmark X": within this distance at the time limit

  def __post_init__(self):
    if self.query not in ("ensemble", "first"):
      raise ValueError(f"query must be 'ensemble' or 'first', got {self.query!r}")


PROTOCOL = ToyProtocol()
PROBE_CLASSES = ("reach_A", "reach_B", "reach_C", "toggle", "none")


@functools.lru_cache(maxsize=None)
def _evaluator(model: ModelConfig, env: toy.ToySkillsConfig, query: str, fixed: bool):
  """A jitted (params, key, tasks [B], routing [K]) -> rollout arrays; `fixed`: routing replaces
  the router's (ignored otherwise). One compile per model, shared by seeds and tasks."""
  policy = Policy(model)

  @jax.jit
  def run(params, key, tasks, routing_weights):
    state = toy.reset_batch(env, key, tasks)
    b, c, a = tasks.shape[0], model.chunk, model.action_dim

    def controller(buf, state, t):
      obs = jax.vmap(toy.observe)(state)
      pred, r = policy.apply({"params": params}, obs, routing_weights if fixed else None, method=Policy.predict)
      if query == "ensemble":
        action, buf = temporal_ensemble(buf, pred, t)
      else:
        action = pred[:, 0]
      info = {}
      if r is not None:  # [B, K], or per chunk step [B, chunk, K]: the weights of the step run now
        info["routing"] = r.reshape(b, -1, r.shape[-1])[:, 0]
      return action, buf, info

    final, traj = toy.rollout(env, controller, jnp.zeros((b, c, c, a), jnp.float32), state)
    toggled = (traj.obs["joint_pos"][..., 2] != 0).any(1) | (final.grip != 0)
    xy = traj.obs["joint_pos"][..., :2]
    out = dict(success=final.success, stage=final.stage, label=traj.label,
               step_stage=traj.obs["object_state"][..., toy.STAGE_BITS].argmax(-1),
               quadrant=(xy[..., 0] > 0).astype(jnp.int32) + 2 * (xy[..., 1] > 0), active=traj.active,
               final_pos=final.pos, landmarks=final.landmarks, toggled=toggled)
    if "routing" in traj.info:
      out["routing"] = traj.info["routing"]
    return out

  return run


def eval_tasks(model: ModelConfig, params, tasks: Sequence[int], trials: int, seed: int,
               routing_weights=None, proto: ToyProtocol = PROTOCOL) -> tuple[dict, dict]:
  """Closed loop on `tasks` (indices), `trials` each, from the starts of `seed`: (success per
  task name, the arrays, with `task` [B])."""
  task_ids = np.repeat(np.asarray(tasks, np.int32), trials)
  run = _evaluator(model, proto.env, proto.query, routing_weights is not None)
  r = (jnp.zeros((model.plug.num_skills,), jnp.float32) if routing_weights is None
       else jnp.asarray(routing_weights, jnp.float32))
  out = jax.device_get(run(params, jax.random.PRNGKey(seed), jnp.asarray(task_ids), r))
  rates = {toy.task_id(t): float(out["success"][task_ids == t].mean()) for t in tasks}
  return rates, dict(out, task=task_ids)


def stage_progress(out: dict) -> dict:
  """Per task, the mean fraction of its stages done by the time limit: a finer score than
  success where success is rare (an unseen task whose first stage is done scores 1/2 or 1/3)."""
  done = np.asarray(out["stage"]) / toy.TASK_LENGTH[out["task"]]
  return {toy.task_id(t): float(done[out["task"] == t].mean()) for t in np.unique(out["task"])}


def probe_classes(out: dict, radius: float) -> np.ndarray:
  """What each rollout did: its landmark (0-2) if it ended within `radius` of one, else 3 if
  the gripper switched, else 4 (nothing)."""
  d = np.linalg.norm(out["landmarks"] - out["final_pos"][:, None], axis=-1)
  near = d.argmin(-1)
  return np.where(d.min(-1) < radius, near, np.where(out["toggled"], 3, 4))


def fixed_skill_probe(model: ModelConfig, params, seed: int, proto: ToyProtocol = PROTOCOL) -> dict:
  """Each skill alone (and uniform routing) on the seen tasks: what the robot does, and success."""
  k = model.plug.num_skills
  skills = {}
  for i in range(k):
    rates, out = eval_tasks(model, params, toy.SEEN, proto.probe_trials, seed, np.eye(k)[i], proto)
    cls = probe_classes(out, proto.probe_radius)
    frac = np.bincount(cls, minlength=len(PROBE_CLASSES)) / len(cls)
    top = int(frac.argmax())
    skills[f"skill{i}"] = dict(fractions=dict(zip(PROBE_CLASSES, frac.tolist())), primitive=PROBE_CLASSES[top],
                               purity=float(frac[top]), toggled=float(out["toggled"].mean()),
                               success=float(np.mean(list(rates.values()))))
  pure = {s["primitive"] for s in skills.values() if s["purity"] >= 0.8 and s["primitive"] != "none"}
  uniform, _ = eval_tasks(model, params, toy.SEEN, proto.probe_trials, seed, np.full(k, 1.0 / k), proto)
  return dict(skills=skills, distinct_pure_primitives=len(pure),
              mean_purity=float(np.mean([s["purity"] for s in skills.values()])),
              uniform_success=float(np.mean(list(uniform.values()))),
              note=f"routing fixed for the whole time limit, {proto.probe_trials} trials per seen task; "
                   f"a skill is pure when >= 80% of its rollouts do one primitive")


def routing_report(out: dict) -> dict:
  """`routing.routing_stats` of the queries made while the task ran (closed loop), NMI of their
  argmax against the primitive (nmi), the task (nmi_task, where there are several), the stage
  and the robot's quadrant, and the mean weights per primitive [primitives, K]."""
  keep = out["active"] & (out["label"] >= 0)
  r, lab = np.asarray(out["routing"], np.float64)[keep], out["label"][keep]
  chosen = r.argmax(-1)
  rep = routing.routing_stats(r)
  rep["nmi"] = routing.nmi(chosen, lab)
  task = np.broadcast_to(out["task"][:, None], keep.shape)[keep]
  if len(np.unique(task)) > 1:
    rep["nmi_task"] = routing.nmi(chosen, task)
  rep["nmi_stage"] = routing.nmi(chosen, out["step_stage"][keep])
  rep["nmi_quadrant"] = routing.nmi(chosen, out["quadrant"][keep])
  rep["weights_by_primitive"] = {toy.PRIMITIVES[p]: r[lab == p].mean(0).tolist() for p in range(len(toy.PRIMITIVES))
                                 if (lab == p).any()}
  rep["queries"] = int(keep.sum())
  return rep


def _task_arrays(out: dict, task: int) -> dict:
  rows = out["task"] == task
  return {k: np.asarray(v)[rows] for k, v in out.items()}


def _result(task: int, out: dict, trials: int, seed: int, routing_file: Path | None) -> dict:
  """One task's result in `protocol.evaluate_task`'s format, with the toy's extras."""
  success = np.asarray(out["success"], bool)
  length = np.asarray(out["active"]).sum(1).astype(np.int32)  # one query per control step
  first = np.where(success, length, -1)
  r = dict(task=toy.task_id(task), abbr=toy.task_name(task), trials=trials, seed=seed, backend="toy",
           success_rate=float(success.mean()), successes=int(success.sum()),
           mean_queries_success=float(length[success].mean()) if success.any() else None,
           mean_steps_success=float(length[success].mean()) if success.any() else None,
           trial_success=success.tolist(), trial_queries=length.tolist(), trial_success_step=first.tolist(),
           stage_progress=stage_progress(out)[toy.task_id(task)])
  if "routing" in out:
    weights = np.where(out["active"][..., None], np.asarray(out["routing"], np.float64), np.nan)  # [B, T, K]
    q = routing.queries_of(weights)
    r.update(mean_weights=q.mean(0).tolist(), diagnostics=dict(routing.routing_stats(q), queries=int(len(q))),
             toy_routing=routing_report(out))
    if routing_file is not None:
      protocol.write_routing(routing_file, toy.task_id(task), [weights.transpose(1, 0, 2)], trials, success,
                             first, length)
  return r


def _eval_path(run: Path, name: str, exp) -> Path:
  return Path(run) / "eval" / f"{name}_trials{exp.trials}_seed{exp.eval_seed}.json"


def evaluated(run: Path, tasks, exp, name: str, source: Path, extra: dict | None = None) -> list[dict]:
  """`experiments.pipeline.evaluated` for a toy run: the closed-loop results of `run` on `tasks`
  (toy task names, one batch, so trial i of a task is the same start for every run), read back
  when this evaluation was already written; `source`: the run whose row they are tabulated under."""
  path = _eval_path(run, name, exp)
  if path.exists():
    return json.loads(path.read_text())["results"]
  t0 = time.time()
  cfg, params, _ = loop.load_params(run)
  row = groups.row_fields(run_files.read_config(source), experiment.read_record(source))
  ids = [toy.TASK_IDS[t] for t in tasks]
  _, out = eval_tasks(cfg.model, params, ids, exp.trials, exp.eval_seed)
  results = []
  for t in ids:
    file = path.with_name(f"{path.stem}_{toy.task_id(t)}.routing.npz") if cfg.model.is_skillplug else None
    r = _result(t, _task_arrays(out, t), exp.trials, exp.eval_seed, file)
    r.update(run=str(run), **row, trained_on="toy", routing_file=str(file) if file else None,
             toy_protocol=dataclasses.asdict(PROTOCOL), **(extra or {}))
    results.append(r)
  wall = round(time.time() - t0, 1)
  results = [dict(r, wall_s=wall) for r in results]
  write_json_atomic(path, dict(results=results))
  return results


def run_extras(run: Path, exp) -> dict:
  """The toy's numbers of a multi-task run beyond its per-task results (module docstring):
  routing over the seen tasks together, the fixed-skill probe, zero-shot on the unseen tasks;
  read back when already written."""
  path = _eval_path(run, "toy_extras", exp)
  if path.exists():
    return json.loads(path.read_text())
  cfg, params, _ = loop.load_params(run)
  zero, zero_out = eval_tasks(cfg.model, params, toy.UNSEEN, exp.trials, exp.eval_seed)
  extras = dict(zero_shot=zero, zero_shot_progress=stage_progress(zero_out),
                toy_protocol=dataclasses.asdict(PROTOCOL))
  if cfg.model.is_skillplug:
    _, out = eval_tasks(cfg.model, params, toy.SEEN, exp.trials, exp.eval_seed)
    extras["toy_routing"] = routing_report(out)
    extras["fixed_skill_probe"] = fixed_skill_probe(cfg.model, params, exp.eval_seed)
  write_json_atomic(path, extras)
  return extras


def mined_label_agreement(cfg) -> dict:
  """How the labels train.skill_labels=toy_targets mines from the demonstrations match the
  primitive (every step of every demonstration `cfg` trains on): NMI and the fraction equal."""
  return label_agreement(toy_train.data_of(cfg))


def label_agreement(data: dict) -> dict:
  """`mined_label_agreement` of demonstrations as `train.toy.demo_arrays` makes them."""
  keep = np.arange(data["label"].shape[1])[None] < data["length"][:, None]
  mined, label = data["mined"][keep], data["label"][keep]
  return dict(labeller="toy_targets", nmi=routing.nmi(mined, label), equal=float(np.mean(mined == label)))

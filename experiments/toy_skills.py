"""make toy-skills   (python -m experiments.toy_skills --out results/toy_skills)

The skill library's fast screen and regression test (issue 27): ACT and
ACT+SkillPlug variants on the toy point-robot problem (envs/toy_skills.py),
whose four behaviour primitives are known, in minutes on a CPU.

Per variant and training seed:
1. multi-task training on the 6 seen tasks (50 expert demos each, in memory:
   no dataset on disk) with the project's loss (`losses.total_loss`),
   optimiser (`train.loop.optimizer`) and step (`train.loop.make_train_step`);
2. closed-loop evaluation (one jitted `lax.scan` over control steps of
   vmapped environments, the policy queried every step, its first action
   run; ACT's temporal ensembling is an option) on every seen task: success per task, and the routing of
   every query while the task was running, scored against the primitive the
   environment was executing (the label of that step);
3. the fixed-skill probe: closed loop on the seen tasks with the routing
   fixed one-hot on each skill k for the whole time limit; what the robot
   does (ends within `probe_radius` of landmark A, B or C; else toggles the
   gripper; else nothing) says whether each skill alone is one primitive;
   plus uniform routing (1/K each), which a router that learned nothing
   would give;
4. zero-shot (the multi-task parameters on the unseen tasks) and
   few-shot: from those parameters, one fine-tune per unseen task (10
   demos) of the paper's groups (ACT: action_head; ACT+SkillPlug:
   action_head + router; with model.plug_site=decoder: action_proj, and
   action_proj + router), then its closed-loop evaluation. Besides success,
   the mean fraction of each task's stages done ("stages %"), which ranks
   arms where success is rare.

Routing statistics (closed-loop queries of step 2, while the task ran):
  routing_entropy_per_query  mean_q H(r_q) / log K     (1: every query uniform)
  usage_entropy              H(mean_q r_q) / log K     (1: every skill used alike)
  effective_skills           exp H(mean_q r_q)         (1..K)
  nmi                        normalised mutual information (arithmetic mean of
                             the entropies, sklearn's default) between argmax_k r_q
                             and the primitive label of that step (nmi_task, nmi_stage,
                             nmi_quadrant: the same against the task, the stage index and
                             the robot's quadrant of the table, what else routing could follow)
Variants are override strings in the `--set` syntax (train/config.py
`override`) on the toy's TrainConfig; one naming an unknown setting stops the
run with an error naming the variant and the setting.

Writes OUT/summary.json and OUT/summary.md (the table, also printed).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from envs import toy_skills as toy
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.data import segments
from skillplug_jax.evaluate.policy_controller import temporal_ensemble
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import loop
from skillplug_jax.train.config import TrainConfig, override


@dataclasses.dataclass(frozen=True)
class ToyVariant:
  """One arm: `overrides` (train/config.py syntax, dotted keys on the TrainConfig) make it."""
  name: str
  overrides: tuple[str, ...] = ()
  label: str = ""
  fewshot: tuple[str, ...] = ()  # the groups few-shot retrains, when not the paper's (fewshot_groups)
  fewshot_overrides: tuple[str, ...] = ()  # TrainConfig overrides of the few-shot fine-tune alone


# Every arm the screen knows; --variants picks some (default: DEFAULT_VARIANTS). Names shared with
# experiments/configs/skill_library.py (the `cpu`-preset screen) mean the same overrides there.
USAGE = ("loss.usage=0.5",)
ORACLE = "loss.router_label=1.0"
MINED = "skill_labels=toy_targets"
CUE = f"model.router_cue_slots={toy.OBJECT_STATE_DIM // toy.SLOT - 3}"  # the slots after the 3 landmarks
VARIANTS = (
    ToyVariant("act", ("model.policy=act",), "ACT"),
    ToyVariant("skillplug_paper", (), "ACT+SkillPlug (paper)"),
    # readings within the paper's text
    ToyVariant("act_decoder", ("model.policy=act", "model.plug_site=decoder"), "ACT, light head (action_proj)"),
    ToyVariant("decoder", ("model.plug_site=decoder",), "plug on the decoder"),
    ToyVariant("tokens", ("model.interactor=skill_tokens", "model.skill_offset=none", "model.router_input=no_style"),
               "skill tokens, no z offset, no style"),
    ToyVariant("skill_tokens", ("model.interactor=skill_tokens",), "skill-token interactor"),
    ToyVariant("film", ("model.interactor=film",), "FiLM interactor"),
    ToyVariant("z_mean", ("model.skill_offset=mean",), "z at its mean"),
    ToyVariant("z_none", ("model.skill_offset=none",), "no z offset"),
    ToyVariant("no_style", ("model.router_input=no_style",), "router without style"),
    ToyVariant("act_per_object", ("model.policy=act", "model.object_tokens=per_object"), "ACT, token per object"),
    ToyVariant("per_object", ("model.object_tokens=per_object",), "token per object"),
    # remedies beyond the paper (ours)
    ToyVariant("usage", USAGE, "usage 0.5 (ours)"),
    ToyVariant("usage_sq", USAGE + ("loss.sd_kind=squared", "loss.sd_usage_weighted=true"),
               "usage 0.5 + squared SD, r-weighted (ours)"),
    ToyVariant("sd_squared", ("loss.sd_kind=squared",), "SD on squared cosines (ours)"),
    ToyVariant("sd_gram", ("loss.sd_kind=gram",), "SD on the Gram matrix (ours)"),
    ToyVariant("sd_gram_usage", ("loss.sd_kind=gram", "loss.sd_usage_weighted=true"), "SD Gram, r-weighted (ours)"),
    ToyVariant("posterior", ("model.fusion_source=posterior",), "fusion on q(k|tau), router distilled (ours)"),
    ToyVariant("top1", USAGE + ("model.routing=top1",), "top-1 + usage (ours)"),
    ToyVariant("top1_only", ("model.routing=top1",), "top-1 (ours)"),
    ToyVariant("load_balance", ("loss.load_balance=0.01",), "load balance 0.01 (ours)"),
    ToyVariant("router_z", ("loss.router_z=0.001",), "router z-loss 0.001 (ours)"),
    ToyVariant("decoder_usage", ("model.plug_site=decoder",) + USAGE, "decoder + usage 0.5 (ours)"),
    ToyVariant("decoder_top1", ("model.plug_site=decoder", "model.routing=top1") + USAGE,
               "decoder + top-1 + usage 0.5 (ours)"),
    ToyVariant("tokens_usage", ("model.interactor=skill_tokens", "model.skill_offset=none",
                                "model.router_input=no_style") + USAGE, "skill tokens, no z, no style + usage 0.5 (ours)"),
    ToyVariant("per_object_usage", ("model.object_tokens=per_object",) + USAGE, "token per object + usage 0.5 (ours)"),
    # the task cue (program and stage) read by the router alone: the decoder learns what to do
    # next only through the routing (ours)
    ToyVariant("cue", (CUE,), "cue to the router only (ours)"),
    ToyVariant("cue_top1", (CUE, "model.routing=top1"), "cue to the router only, top-1 (ours)"),
    ToyVariant("cue_top1_router", (CUE, "model.routing=top1"), "cue to the router only, top-1; few-shot: router (ours)",
               fewshot=("router",)),
    # ... with one token per landmark, so that a skill's query offset can pick which one to reach
    ToyVariant("cue_per_object", (CUE, "model.object_tokens=per_object"), "cue to the router only, token per object (ours)"),
    ToyVariant("cue_per_object_top1", (CUE, "model.object_tokens=per_object", "model.routing=top1"),
               "cue to the router only, token per object, top-1 (ours)"),
    ToyVariant("cue_per_object_sq", (CUE, "model.object_tokens=per_object", "loss.sd_kind=squared"),
               "cue to the router only, token per object, squared SD (ours)"),
    ToyVariant("cue_tokens", (CUE, "model.object_tokens=per_object", "model.interactor=skill_tokens",
                              "model.skill_offset=none"), "cue to the router only, token per object, skill tokens (ours)"),
    # oracle routing (a diagnostic, not a method: it reads the primitive label, in pretraining and
    # in the few-shot fine-tune): what the library does when the router has the partition the
    # unsupervised variants never find
    ToyVariant("oracle", (ORACLE,), "router told the primitive (oracle)"),
    ToyVariant("oracle_per_object", (ORACLE, "model.object_tokens=per_object"),
               "router told the primitive, token per object (oracle)"),
    ToyVariant("oracle_cue_per_object", (ORACLE, CUE, "model.object_tokens=per_object"),
               "router told the primitive, cue to the router only, token per object (oracle)"),
    ToyVariant("oracle_cue_per_object_router", (ORACLE, CUE, "model.object_tokens=per_object"),
               "router told the primitive, cue to the router only, token per object; few-shot: router (oracle)",
               fewshot=("router",)),
    # ... and the few-shot router trained by reconstruction alone: the unseen tasks' labels unused
    ToyVariant("oracle_cue_per_object_router_unlabelled", (ORACLE, CUE, "model.object_tokens=per_object"),
               "router told the primitive in pretraining only, cue to the router only, token per object; "
               "few-shot: router, no labels (oracle)", fewshot=("router",), fewshot_overrides=("loss.router_label=0",)),
    # labels mined from the demonstrations (data/segments.py: the landmark the commanded target
    # is nearest, or the gripper while it is commanded to switch), no ground truth read (ours)
    ToyVariant("mined", (ORACLE, MINED), "router trained on mined labels (ours)"),
    ToyVariant("mined_cue_per_object_router", (ORACLE, MINED, CUE, "model.object_tokens=per_object"),
               "router trained on mined labels, cue to the router only, token per object; few-shot: router (ours)",
               fewshot=("router",)),
)
DEFAULT_VARIANTS = ("act", "skillplug_paper")


def toy_train_config() -> TrainConfig:
  """The toy's model and optimisation: the quick preset's sizes (FF 128), chunk 8, no dropout, raw inputs.

  3000 steps of batch 64: ACT reaches 85-90% multi-task (held-out position L1 0.05); batch 128
  or FF 256 gained a few points for twice the time.

  Dropout 0: the reaches need targets within 0.1, and at dropout 0.1 ACT's position L1 after
  3000 steps was 0.1 (0.04 without).

  Inputs and actions are not normalised: they already lie in [-1, 1] (gripper
  {0, 1}, the task's program and stage one-hot), and z-scoring one-hot bits that are rare in the
  seen demos (std clipped to 0.01) would feed the frozen encoder values of up to 100.
  """
  model = ModelConfig(use_images=False, joint_dim=toy.JOINT_DIM, action_dim=toy.ACTION_DIM, chunk=8,
                      hidden=64, heads=4, ff=128, enc_layers=2, dec_layers=2, cvae_enc_layers=1,
                      num_skills=4, skill_latent_dim=16, alignment_dim=32, normalize_object_state=False,
                      dropout=0.0)
  return TrainConfig(preset="toy_skills", model=model, taskset="toy_skills", batch_size=64, lr=1e-3,
                     warmup_steps=100, lr_schedule="cosine", max_steps=3000, weight_decay=1e-4)


@dataclasses.dataclass(frozen=True)
class ToyExperiment:
  """The toy screen's settings. `--set KEY=VALUE`: a key whose first part is a field here sets it
  (`fewshot_steps=100`, `train.lr=3e-4`); any other key is a TrainConfig key (`model.num_skills=6`,
  `loss.sd=0`), applied to every variant before the variant's own overrides."""
  train: TrainConfig = dataclasses.field(default_factory=toy_train_config)
  env: toy.ToySkillsConfig = toy.ToySkillsConfig()
  variants: tuple[str, ...] = DEFAULT_VARIANTS  # names from VARIANTS, or 'all'
  seeds: tuple[int, ...] = (0,)  # training seeds (data and evaluation starts are shared: paired)
  # Expert demonstrations per seen task. 500, not 50: with 50 (300 landmark layouts) ACT
  # memorised the layouts (train L1 0.02, closed loop 8%); with 500 held-out L1 equals train L1.
  demos_seen: int = 500
  demos_unseen: int = 10  # per unseen task (few-shot)
  demo_seed: int = 0
  eval_trials: int = 50  # closed-loop episodes per task
  eval_seed: int = 1000
  # 'first': query every step, run the chunk's first action; 'ensemble': ACT's temporal ensembling
  # (it mixes stale absolute targets: ACT 43% against 54% with 'first' at radius 0.05).
  query: str = "first"
  fewshot_steps: int = 300  # per unseen task (about 80 epochs of its 10 demos)
  fewshot_act: tuple[str, ...] = ("action_head",)
  fewshot_skillplug: tuple[str, ...] = ("action_head", "router")
  fewshot_act_decoder: tuple[str, ...] = ("action_proj",)  # when model.plug_site=decoder
  fewshot_skillplug_decoder: tuple[str, ...] = ("action_proj", "router")
  probe_trials: int = 10  # per seen task, per fixed routing
  probe_radius: float = 0.15  # "ends at landmark X": within this distance at the time limit
  steps_per_call: int = 100  # training steps per jitted call (one lax.scan)

  def __post_init__(self):
    if self.query not in ("ensemble", "first"):
      raise ValueError(f"query must be 'ensemble' or 'first', got {self.query!r}")


def apply_settings(exp: ToyExperiment, assignments: Sequence[str]) -> ToyExperiment:
  """--set: ToyExperiment fields by name, everything else on `exp.train`."""
  own = {f.name for f in dataclasses.fields(ToyExperiment)}
  for item in assignments:
    key = item.split("=", 1)[0].strip()
    if key.split(".")[0] in own:
      exp = override(exp, [item])
    else:
      exp = dataclasses.replace(exp, train=override(exp.train, [item]))
  return exp


def selected_variants(exp: ToyExperiment) -> list[ToyVariant]:
  by_name = {v.name: v for v in VARIANTS}
  if exp.variants == ("all",):
    return list(VARIANTS)
  unknown = [n for n in exp.variants if n not in by_name]
  if unknown:
    raise ValueError(f"unknown variant(s) {unknown}; known: {', '.join(by_name)}, or 'all'")
  return [by_name[n] for n in exp.variants]


# --------------------------------------------------------------------------- routing statistics

def entropy(p: np.ndarray) -> np.ndarray:
  """Shannon entropy (nats) of each row of p [..., K]."""
  p = np.clip(np.asarray(p, np.float64), 1e-12, 1.0)
  return -(p * np.log(p)).sum(-1)


def routing_stats(routing: np.ndarray) -> dict:
  """routing [Q, K], one row per query: the three library-usage numbers (module docstring)."""
  r = np.asarray(routing, np.float64).reshape(-1, np.shape(routing)[-1])
  k = r.shape[-1]
  h_mean = float(entropy(r.mean(0)))
  return dict(routing_entropy_per_query=float(entropy(r).mean() / math.log(k)),
              usage_entropy=h_mean / math.log(k), effective_skills=math.exp(h_mean),
              mean_weights=r.mean(0).tolist())


def nmi(x: np.ndarray, y: np.ndarray) -> float:
  """Normalised mutual information of two label arrays: I(x; y) / ((H(x) + H(y)) / 2).

  1 for a one-to-one mapping, ~0 for independent labels; 0 when both are constant.
  """
  x, y = np.asarray(x).ravel(), np.asarray(y).ravel()
  _, xi = np.unique(x, return_inverse=True)
  _, yi = np.unique(y, return_inverse=True)
  joint = np.zeros((xi.max() + 1, yi.max() + 1))
  np.add.at(joint, (xi, yi), 1.0)
  joint /= joint.sum()
  px, py = joint.sum(1), joint.sum(0)
  nz = joint > 0
  mi = float((joint[nz] * np.log(joint[nz] / (px[:, None] * py[None, :])[nz])).sum())
  hx, hy = float(entropy(px)), float(entropy(py))
  return 0.0 if hx + hy <= 0 else max(0.0, mi / (0.5 * (hx + hy)))


def mean_se(values: Sequence[float]) -> dict:
  v = np.asarray(values, np.float64)
  se = float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else None
  return dict(mean=float(v.mean()), se=se, values=v.tolist())


# --------------------------------------------------------------------------- data and training

def demo_arrays(env: toy.ToySkillsConfig, key, tasks: Sequence[int], per_task: int, chunk: int) -> dict:
  """Expert episodes as padded arrays: obs [E, T, ...], actions [E, T + chunk, 3] (the last
  action repeated past the end, masked in training), length [E], label [E, T], task [E]."""
  task_ids = np.repeat(np.asarray(tasks, np.int32), per_task)
  final, traj = jax.jit(lambda k: toy.demonstrations(env, k, task_ids))(key)
  if not bool(np.all(np.asarray(final.success))):
    raise RuntimeError("the toy expert failed an episode; its demonstrations would be wrong")
  length = np.asarray(traj.active).sum(1).astype(np.int32)
  actions = np.asarray(traj.action)
  last = actions[np.arange(len(length)), length - 1]
  pad = np.repeat(last[:, None], chunk, axis=1)
  actions = np.concatenate([actions, pad], axis=1)
  t = np.arange(actions.shape[1])[None, :, None]
  actions = np.where(t < length[:, None, None], actions, last[:, None])
  joint_pos, object_state = np.asarray(traj.obs["joint_pos"]), np.asarray(traj.obs["object_state"])
  mined = np.stack([segments.toy_targets(joint_pos[e], object_state[e], actions[e, :joint_pos.shape[1]])
                    for e in range(len(length))])
  return dict(joint_pos=joint_pos, object_state=object_state, actions=actions.astype(np.float32),
              length=length, label=np.asarray(traj.label), mined=mined, task=task_ids)


def sample_batch(data: dict, key, batch_size: int, chunk: int) -> dict:
  """ACT's sampling: a random episode, a random step of it, the chunk from there (masked past the end)."""
  k_ep, k_t = jax.random.split(key)
  ep = jax.random.randint(k_ep, (batch_size,), 0, data["length"].shape[0])
  length = data["length"][ep]
  t = jnp.floor(jax.random.uniform(k_t, (batch_size,)) * length).astype(jnp.int32)
  chunk_of = lambda a, s: jax.lax.dynamic_slice_in_dim(a, s, chunk, axis=0)
  batch = {"joint_pos": data["joint_pos"][ep, t], "object_state": data["object_state"][ep, t],
           "actions": jax.vmap(chunk_of)(data["actions"][ep], t),
           "action_mask": (t[:, None] + jnp.arange(chunk)[None]) < length[:, None]}
  if "label" in data:  # the step's primitive or mined label, which only loss.router_label reads
    batch["skill_label"] = data["label"][ep, t]
  return batch


def example_batch(model: ModelConfig) -> dict:
  return {"joint_pos": jnp.zeros((2, model.joint_dim)), "object_state": jnp.zeros((2, toy.OBJECT_STATE_DIM)),
          "actions": jnp.zeros((2, model.chunk, model.action_dim)),
          "action_mask": jnp.ones((2, model.chunk), bool)}


def init_params(model: ModelConfig, key):
  k_params, k_drop, k_sample = jax.random.split(key, 3)
  return Policy(model).init({"params": k_params, "dropout": k_drop, "sample": k_sample},
                            example_batch(model), train=True)["params"]


@functools.lru_cache(maxsize=None)
def _trainer(cfg: TrainConfig, steps_per_call: int):
  """A jitted (state, data, key) -> (state, metrics) running `steps_per_call` steps of `cfg`.

  Cached per config (seed excluded: it arrives in `key`), so seeds and few-shot tasks share it.
  """
  like = jax.eval_shape(lambda: init_params(cfg.model, jax.random.PRNGKey(0)))
  tx = loop.optimizer(cfg, like, cfg.max_steps)

  @jax.jit
  def run(state, data, key):
    data_key, step_key = jax.random.split(key)
    train_step = loop.make_train_step(cfg, tx, step_key)

    def body(state, _):
      batch = sample_batch(data, jax.random.fold_in(data_key, state.step), cfg.batch_size, cfg.model.chunk)
      return train_step(state, batch)

    state, metrics = jax.lax.scan(body, state, None, length=steps_per_call)
    return state, jax.tree.map(jnp.mean, metrics)

  return tx, run


def train(cfg: TrainConfig, params, data: dict, key, steps_per_call: int, desc: str = "",
          progress: bool = True) -> tuple[object, dict]:
  """`cfg.max_steps` steps from `params` (frozen groups: `cfg.trainable`); the last call's mean losses.

  The batches' `skill_label` (read only by loss.router_label) is the primitive, or with
  train.skill_labels=toy_targets the label mined from the demonstration (data/segments.py)."""
  data_all = data
  cfg = dataclasses.replace(cfg, seed=0)
  calls = max(1, math.ceil(cfg.max_steps / steps_per_call))
  tx, run = _trainer(cfg, steps_per_call)
  state = loop.TrainState(jnp.zeros((), jnp.int32), params, tx.init(params))
  labels = {"": "label", "toy_targets": "mined"}.get(cfg.skill_labels)
  if labels is None:
    raise ValueError(f"train.skill_labels={cfg.skill_labels!r}: the toy's labeller is 'toy_targets' "
                     "('': its ground-truth primitive)")
  data = {k: jnp.asarray(v) for k, v in data.items() if k in ("joint_pos", "object_state", "actions", "length")}
  data["label"] = jnp.asarray(data_all[labels])
  metrics = {}
  for _ in tqdm(range(calls), desc=desc, unit=f"x{steps_per_call}step", file=sys.stderr,
                disable=not progress, leave=False, dynamic_ncols=True):
    state, metrics = jax.block_until_ready(run(state, data, key))  # so the bar shows real progress
  metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
  if not all(math.isfinite(v) for v in metrics.values()):
    raise FloatingPointError(f"non-finite training loss: {metrics}")
  return state.params, metrics


# --------------------------------------------------------------------------- closed loop

@functools.lru_cache(maxsize=None)
def _evaluator(model: ModelConfig, env: toy.ToySkillsConfig, query: str, fixed: bool):
  """A jitted (params, key, tasks [B], routing [K]) -> rollout arrays; `fixed`: routing replaces
  the router's (ignored otherwise). One compile per model, shared by seeds and tasks."""
  policy = Policy(model)

  @jax.jit
  def run(params, key, tasks, routing):
    state = toy.reset_batch(env, key, tasks)
    b, c, a = tasks.shape[0], model.chunk, model.action_dim

    def controller(buf, state, t):
      obs = jax.vmap(toy.observe)(state)
      pred, r = policy.apply({"params": params}, obs, routing if fixed else None, method=Policy.predict)
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
               quadrant=(xy[..., 0] > 0).astype(jnp.int32) + 2 * (xy[..., 1] > 0), active=traj.active, final_pos=final.pos,
               landmarks=final.landmarks, toggled=toggled)
    if "routing" in traj.info:
      out["routing"] = traj.info["routing"]
    return out

  return run


def rollouts(model: ModelConfig, env: toy.ToySkillsConfig, query: str, params, key, tasks,
             routing=None) -> dict:
  run = _evaluator(model, env, query, routing is not None)
  k = model.num_skills
  r = jnp.zeros((k,), jnp.float32) if routing is None else jnp.asarray(routing, jnp.float32)
  return jax.device_get(run(params, key, jnp.asarray(tasks, jnp.int32), r))


def eval_tasks(exp: ToyExperiment, model: ModelConfig, params, tasks: Sequence[int], trials: int,
               routing=None) -> tuple[dict, dict]:
  """Closed loop on `tasks`, `trials` each, from the shared evaluation starts: (per-task success, arrays)."""
  task_ids = np.repeat(np.asarray(tasks, np.int32), trials)
  out = rollouts(model, exp.env, exp.query, params, jax.random.PRNGKey(exp.eval_seed), task_ids, routing)
  rates = {toy.task_name(t): float(out["success"][task_ids == t].mean()) for t in tasks}
  return rates, dict(out, task=task_ids)


def stage_progress(out: dict) -> dict:
  """Per task, the mean fraction of its stages done by the time limit: a finer score than
  success where success is rare (an unseen task whose first stage is done scores 1/2 or 1/3)."""
  done = np.asarray(out["stage"]) / toy.TASK_LENGTH[out["task"]]
  return {toy.task_name(t): float(done[out["task"] == t].mean()) for t in np.unique(out["task"])}


PROBE_CLASSES = ("reach_A", "reach_B", "reach_C", "toggle", "none")


def probe_classes(out: dict, radius: float) -> np.ndarray:
  """What each rollout did: its landmark (0-2) if it ended within `radius` of one, else 3 if
  the gripper switched, else 4 (nothing)."""
  d = np.linalg.norm(out["landmarks"] - out["final_pos"][:, None], axis=-1)
  near = d.argmin(-1)
  return np.where(d.min(-1) < radius, near, np.where(out["toggled"], 3, 4))


def fixed_skill_probe(exp: ToyExperiment, model: ModelConfig, params) -> dict:
  """Each skill alone (and uniform routing) on the seen tasks: what the robot does, and success."""
  k = model.num_skills
  skills = {}
  for i in range(k):
    rates, out = eval_tasks(exp, model, params, toy.SEEN, exp.probe_trials, np.eye(k)[i])
    cls = probe_classes(out, exp.probe_radius)
    frac = np.bincount(cls, minlength=len(PROBE_CLASSES)) / len(cls)
    top = int(frac.argmax())
    skills[f"skill{i}"] = dict(fractions=dict(zip(PROBE_CLASSES, frac.tolist())), primitive=PROBE_CLASSES[top],
                               purity=float(frac[top]), toggled=float(out["toggled"].mean()),
                               success=float(np.mean(list(rates.values()))))
  pure = {s["primitive"] for s in skills.values() if s["purity"] >= 0.8 and s["primitive"] != "none"}
  uniform, _ = eval_tasks(exp, model, params, toy.SEEN, exp.probe_trials, np.full(k, 1.0 / k))
  return dict(skills=skills, distinct_pure_primitives=len(pure),
              mean_purity=float(np.mean([s["purity"] for s in skills.values()])),
              uniform_success=float(np.mean(list(uniform.values()))),
              note=f"routing fixed for the whole time limit, {exp.probe_trials} trials per seen task; "
                   f"a skill is pure when >= 80% of its rollouts do one primitive")


def routing_report(out: dict, k: int) -> dict:
  """Routing statistics over the queries made while the task ran (closed loop), and the mean
  weights per ground-truth primitive [primitives, K]."""
  keep = out["active"] & (out["label"] >= 0)
  r, lab = out["routing"][keep], out["label"][keep]
  rep = routing_stats(r)
  rep["nmi"] = nmi(r.argmax(-1), lab)
  # what else the choice could follow: the task, the stage index, the robot's quadrant of the table
  task = np.broadcast_to(out["task"][:, None], keep.shape)[keep]
  rep["nmi_task"] = nmi(r.argmax(-1), task)
  rep["nmi_stage"] = nmi(r.argmax(-1), out["step_stage"][keep])
  rep["nmi_quadrant"] = nmi(r.argmax(-1), out["quadrant"][keep])
  rep["weights_by_primitive"] = {toy.PRIMITIVES[p]: r[lab == p].mean(0).tolist() for p in range(len(toy.PRIMITIVES))
                                 if (lab == p).any()}
  rep["queries"] = int(keep.sum())
  return rep


# --------------------------------------------------------------------------- one variant

def variant_config(exp: ToyExperiment, variant: ToyVariant) -> TrainConfig:
  try:
    return override(exp.train, variant.overrides)
  except ValueError as e:
    raise ValueError(f"toy variant {variant.name!r}: {e}") from e


def fewshot_groups(exp: ToyExperiment, cfg: TrainConfig, variant: ToyVariant | None = None) -> tuple[str, ...]:
  if variant is not None and variant.fewshot:
    return variant.fewshot
  decoder = cfg.model.plug_site == "decoder"
  if cfg.model.is_skillplug:
    return exp.fewshot_skillplug_decoder if decoder else exp.fewshot_skillplug
  return exp.fewshot_act_decoder if decoder else exp.fewshot_act


def fewshot_config(exp: ToyExperiment, cfg: TrainConfig, variant: ToyVariant | None = None) -> TrainConfig:
  """The fine-tune on an unseen task's demonstrations: `cfg` with the variant's few-shot
  overrides, its trainable groups and the few-shot step count."""
  groups = fewshot_groups(exp, cfg, variant)
  return dataclasses.replace(override(cfg, variant.fewshot_overrides) if variant else cfg,
                             trainable=tuple(sorted(groups)), max_steps=exp.fewshot_steps,
                             warmup_steps=min(cfg.warmup_steps, exp.fewshot_steps // 10))


def run_seed(exp: ToyExperiment, cfg: TrainConfig, seed: int, data: dict, progress: bool,
             variant: ToyVariant | None = None) -> dict:
  """Train one seed of one variant, then evaluate, probe and adapt it."""
  model = cfg.model
  init_key, step_key = jax.random.split(jax.random.PRNGKey(seed))
  t0 = time.perf_counter()
  params, losses = train(cfg, init_params(model, init_key), data["seen"], step_key, exp.steps_per_call,
                         desc=f"train {model.policy} seed {seed}", progress=progress)
  t1 = time.perf_counter()
  rates, out = eval_tasks(exp, model, params, toy.SEEN, exp.eval_trials)
  res = dict(seed=seed, train_losses=losses, multitask=rates, multitask_mean=float(np.mean(list(rates.values()))))
  zero_shot, zero_out = eval_tasks(exp, model, params, toy.UNSEEN, exp.eval_trials)
  res.update(zero_shot=zero_shot, zero_shot_progress=stage_progress(zero_out))
  if model.is_skillplug:
    res["routing"] = routing_report(out, model.num_skills)
    res["fixed_skill_probe"] = fixed_skill_probe(exp, model, params)
  t2 = time.perf_counter()

  fs_cfg = fewshot_config(exp, cfg, variant)
  fs, fs_progress = {}, {}
  for task in toy.UNSEEN:
    adapted, _ = train(fs_cfg, params, data["unseen"][task], jax.random.fold_in(step_key, 1000 + task),
                       exp.steps_per_call, desc=f"few-shot {toy.task_name(task)}", progress=progress)
    rates_fs, out_fs = eval_tasks(exp, model, adapted, (task,), exp.eval_trials)
    fs.update(rates_fs)
    fs_progress.update(stage_progress(out_fs))
  res.update(fewshot=fs, fewshot_mean=float(np.mean(list(fs.values()))), fewshot_progress=fs_progress,
             fewshot_progress_mean=float(np.mean(list(fs_progress.values()))),
             fewshot_trainable=list(fs_cfg.trainable))
  t3 = time.perf_counter()
  res["time_s"] = dict(train=t1 - t0, eval_probe=t2 - t1, fewshot=t3 - t2)
  return res


def aggregate(seeds: list[dict]) -> dict:
  """Mean +- SE over seeds of every number the table reads (None where it has no meaning)."""
  agg = {"multitask_success": dict(mean_se([s["multitask_mean"] for s in seeds]),
                                   per_task={t: mean_se([s["multitask"][t] for s in seeds]) for t in seeds[0]["multitask"]})}
  agg["zero_shot_progress"] = (mean_se([np.mean(list(s["zero_shot_progress"].values())) for s in seeds])
                               if "zero_shot_progress" in seeds[0] else None)
  if "fewshot" in seeds[0]:
    agg["fewshot_success"] = dict(mean_se([s["fewshot_mean"] for s in seeds]),
                                  per_task={t: mean_se([s["fewshot"][t] for s in seeds]) for t in seeds[0]["fewshot"]})
    agg["fewshot_progress"] = mean_se([s["fewshot_progress_mean"] for s in seeds])
  else:
    agg["fewshot_success"] = agg["fewshot_progress"] = None
  for key in ("routing_entropy_per_query", "usage_entropy", "effective_skills", "nmi", "nmi_task", "nmi_stage",
              "nmi_quadrant"):
    agg[key] = mean_se([s["routing"][key] for s in seeds]) if "routing" in seeds[0] and key in seeds[0]["routing"] else None
  if "fixed_skill_probe" in seeds[0]:
    probes = [s["fixed_skill_probe"] for s in seeds]
    agg["fixed_skill_probe"] = dict(
        distinct_pure_primitives=mean_se([p["distinct_pure_primitives"] for p in probes]),
        mean_purity=mean_se([p["mean_purity"] for p in probes]),
        uniform_success=mean_se([p["uniform_success"] for p in probes]),
        per_seed=[{k: (v["primitive"], round(v["purity"], 2)) for k, v in p["skills"].items()} for p in probes])
  else:
    agg["fixed_skill_probe"] = None
  return agg


# --------------------------------------------------------------------------- tables

def _fmt(x, pct=False, digits=2) -> str:
  if x is None:
    return "-"
  scale = 100.0 if pct else 1.0
  s = f"{x['mean'] * scale:.{1 if pct else digits}f}"
  return s if x["se"] is None else s + f" ± {x['se'] * scale:.{1 if pct else digits}f}"


def markdown(summary: dict) -> str:
  lines = ["| variant | multi-task % | zero-shot stages % | few-shot % | few-shot stages % | H(r)/log K | H(mean r)/log K | eff. skills | NMI | "
           "pure skills | uniform-routing % |", "|---" * 11 + "|"]
  for name, v in summary["variants"].items():
    probe = v["fixed_skill_probe"]
    lines.append("| " + " | ".join([
        v["label"] or name, _fmt(v["multitask_success"], True), _fmt(v.get("zero_shot_progress"), True),
        _fmt(v["fewshot_success"], True), _fmt(v.get("fewshot_progress"), True),
        _fmt(v["routing_entropy_per_query"]), _fmt(v["usage_entropy"]), _fmt(v["effective_skills"]),
        _fmt(v["nmi"]), _fmt(probe and probe["distinct_pure_primitives"], digits=1),
        _fmt(probe and probe["uniform_success"], True)]) + " |")
  follows = ["", "What the routing's choice (argmax) follows, NMI against each label:", "",
             "| variant | primitive | task | stage index | robot's quadrant |", "|---" * 5 + "|"]
  for name, v in summary["variants"].items():
    if v.get("nmi"):
      follows.append(f"| {name} | " + " | ".join(_fmt(v.get(k)) for k in ("nmi", "nmi_task", "nmi_stage", "nmi_quadrant"))
                     + " |")
  tasks = [toy.task_name(t) for t in toy.SEEN + toy.UNSEEN]
  per_task = ["", "| variant | " + " | ".join(tasks) + " |", "|---" * (len(tasks) + 1) + "|"]
  for name, v in summary["variants"].items():
    cells = [_fmt(v["multitask_success"]["per_task"][t], True) for t in tasks[:len(toy.SEEN)]]
    fs = v["fewshot_success"]
    cells += [_fmt(fs["per_task"][t], True) if fs else "-" for t in tasks[len(toy.SEEN):]]
    per_task.append(f"| {name} | " + " | ".join(cells) + " |")
  probes = ["", "Fixed-skill probe (seed: skill -> primitive, purity):"]
  for name, v in summary["variants"].items():
    if v["fixed_skill_probe"]:
      for seed, row in zip(v["seeds"], v["fixed_skill_probe"]["per_seed"]):
        probes.append(f"- {name} seed {seed}: " + ", ".join(f"{k} {p} {q:.2f}" for k, (p, q) in row.items()))
  head = [f"Toy skills (envs/toy_skills.py): seen {', '.join(tasks[:len(toy.SEEN)])}; unseen "
          f"{', '.join(tasks[len(toy.SEEN):])} (T = toggle). Mean ± SE over seeds {summary['seeds']}; "
          f"routing over closed-loop queries on the seen tasks; NMI: argmax routing vs the primitive label.", ""]
  return "\n".join(head + lines + follows + per_task + probes) + "\n"


# --------------------------------------------------------------------------- driver

def cpu_name() -> str:
  try:
    for line in subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout.splitlines():
      if line.startswith("Model name"):
        return line.split(":", 1)[1].strip()
  except (OSError, subprocess.CalledProcessError):
    pass
  return platform.processor() or "unknown"


def make_data(exp: ToyExperiment) -> dict:
  key = jax.random.PRNGKey(exp.demo_seed)
  k_seen, k_unseen = jax.random.split(key)
  chunk = exp.train.model.chunk
  seen = demo_arrays(exp.env, k_seen, toy.SEEN, exp.demos_seen, chunk)
  unseen = {t: demo_arrays(exp.env, jax.random.fold_in(k_unseen, t), (t,), exp.demos_unseen, chunk)
            for t in toy.UNSEEN}
  return dict(seen=seen, unseen=unseen)


def mined_label_agreement(data: dict) -> dict:
  """How the labels train.skill_labels=toy_targets mines from the demonstrations match the
  primitive (every step of every demonstration): NMI and the fraction equal."""
  keep = np.arange(data["label"].shape[1])[None] < data["length"][:, None]
  mined, label = data["mined"][keep], data["label"][keep]
  return dict(labeller="toy_targets", nmi=nmi(mined, label), equal=float(np.mean(mined == label)))


def _settings(exp: ToyExperiment) -> dict:
  """What a finished variant's numbers depend on besides its overrides: the config as JSON, less
  the variant and seed lists."""
  cfg = json.loads(json.dumps(dataclasses.asdict(exp)))
  cfg.pop("variants")
  cfg.pop("seeds")
  return cfg


def _differences(a, b, prefix="") -> list[str]:
  """Dotted keys whose values differ between two settings dicts. A key one side lacks is a field
  added since that run, whose default is what the code did before it (the switches' rule:
  docs/training.md), so it is not a difference."""
  if isinstance(a, dict) and isinstance(b, dict):
    return [d for k in sorted(a.keys() & b.keys()) for d in _differences(a[k], b[k], f"{prefix}{k}.")]
  return [] if a == b else [prefix.rstrip(".")]


def finished_variants(exp: ToyExperiment, out: Path) -> dict:
  """Variants OUT/summary.json already holds with these settings, overrides and seeds: a rerun of
  the same command resumes after the last finished variant instead of starting again."""
  path = out / "summary.json"
  if not path.exists():
    return {}
  try:
    old = json.loads(path.read_text())
  except (OSError, json.JSONDecodeError) as e:
    raise ValueError(f"{path} exists but cannot be read ({e}); move it away to start afresh") from e
  if _differences(_settings(exp), {k: v for k, v in old.get("config", {}).items() if k not in ("variants", "seeds")}):
    return {}
  known = {v.name: v for v in VARIANTS}
  return {name: entry for name, entry in old.get("variants", {}).items()
          if name in known and entry.get("overrides") == list(known[name].overrides)
          and entry.get("fewshot_groups", []) == list(known[name].fewshot)
          and entry.get("fewshot_overrides", []) == list(known[name].fewshot_overrides)
          and entry.get("seeds") == list(exp.seeds) and entry.get("status") == "ok"}


def run(exp: ToyExperiment, out: Path, progress: bool = True) -> dict:
  t_start = time.perf_counter()
  done = finished_variants(exp, out)
  data = make_data(exp)
  summary = dict(
      cpu=cpu_name(), devices=[str(d) for d in jax.devices()], seeds=list(exp.seeds),
      tasks=dict(seen={toy.task_name(t): t for t in toy.SEEN}, unseen={toy.task_name(t): t for t in toy.UNSEEN}),
      primitives=list(toy.PRIMITIVES),
      config=dataclasses.asdict(exp),
      routing_measured_on="closed-loop queries on the seen tasks (multi-task evaluation), steps before success",
      mined_labels=mined_label_agreement(data["seen"]),
      variants={})
  for variant in selected_variants(exp):
    if variant.name in done:
      summary["variants"][variant.name] = done[variant.name]
      if progress:
        print(f"{variant.name}: already in {out / 'summary.json'} with these settings; kept", file=sys.stderr)
      continue
    entry = dict(label=variant.label or variant.name, overrides=list(variant.overrides),
                 fewshot_groups=list(variant.fewshot), fewshot_overrides=list(variant.fewshot_overrides))
    cfg = variant_config(exp, variant)
    seeds = [run_seed(exp, cfg, seed, data, progress, variant) for seed in exp.seeds]
    entry.update(status="ok", policy=cfg.model.policy, seeds=list(exp.seeds), **aggregate(seeds), per_seed=seeds)
    summary["variants"][variant.name] = entry
    summary["time_s"] = time.perf_counter() - t_start
    write_json_atomic(out / "summary.json", summary)  # after each variant: a killed run keeps what it had
    if progress:
      print(f"{variant.name}: multi-task {_fmt(entry['multitask_success'], True)}, few-shot "
            f"{_fmt(entry['fewshot_success'], True)}, nmi {_fmt(entry['nmi'])}", file=sys.stderr)
  summary["time_s"] = time.perf_counter() - t_start
  write_json_atomic(out / "summary.json", summary)
  table = markdown(summary)
  write_text_atomic(out / "summary.md", table + f"\nTotal {summary['time_s']:.0f} s on {summary['cpu']}.\n")
  return summary


def combine(sources: Sequence[Path], out: Path) -> dict:
  """One summary of several runs' summary.json (a variant from the first run holding it; listed
  in VARIANTS' order), written like a run's; runs with different settings are refused."""
  merged = None
  for src in sources:
    path = Path(src) / "summary.json"
    if not path.exists():
      raise FileNotFoundError(f"{path} not found")
    summary = json.loads(path.read_text())
    settings = {k: v for k, v in summary["config"].items() if k not in ("variants", "seeds")}
    if merged is None:
      merged, first_settings = dict(summary, variants={}, sources=[], time_s=0.0), settings
    elif _differences(settings, first_settings):
      raise ValueError(f"{path} was run with other settings than {sources[0]} "
                       f"({', '.join(_differences(settings, first_settings))}); not combined")
    merged["sources"].append(str(src))
    merged["time_s"] += summary.get("time_s", 0.0)
    for name, entry in summary["variants"].items():
      merged["variants"].setdefault(name, entry)
  order = {v.name: i for i, v in enumerate(VARIANTS)}
  merged["variants"] = dict(sorted(merged["variants"].items(), key=lambda kv: order.get(kv[0], len(order))))
  merged["seeds"] = sorted({s for v in merged["variants"].values() for s in v["seeds"]})
  write_json_atomic(out / "summary.json", merged)
  write_text_atomic(out / "summary.md", markdown(merged) + f"\nCombined from {', '.join(merged['sources'])} "
                    f"({merged['time_s']:.0f} s of runs on {merged['cpu']}).\n")
  return merged


def parse_args(argv=None):
  p = argparse.ArgumentParser(
      description="The toy skill problem (envs/toy_skills.py): ACT and ACT+SkillPlug variants, "
                  "multi-task and few-shot success, routing statistics, fixed-skill probes.")
  p.add_argument("--out", default="results/toy_skills", help="folder for summary.json and summary.md")
  p.add_argument("--variants", default="",
                 help=f"comma list of variants, or 'all' (default: {','.join(DEFAULT_VARIANTS)}); known: "
                      + ", ".join(v.name for v in VARIANTS))
  p.add_argument("--seeds", default="", help="training seeds, e.g. 0,1,2 (default: 0)")
  p.add_argument("--steps", type=int, default=0, help="multi-task training steps (default: train.max_steps)")
  p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                 help="a ToyExperiment field (fewshot_steps=200, eval_trials=20) or a TrainConfig key "
                      "for every variant (model.num_skills=6, loss.sd=0.1); repeatable")
  p.add_argument("--no-progress", action="store_true")
  p.add_argument("--combine", default="",
                 help="comma list of finished runs' folders: write their variants as one summary to --out "
                      "(no training)")
  return p.parse_args(argv)


def main(argv=None) -> int:
  args = parse_args(argv)
  if args.combine:
    summary = combine([Path(d) for d in args.combine.split(",") if d], Path(args.out))
    print(markdown(summary))
    return 0
  exp = apply_settings(ToyExperiment(), args.set)
  if args.variants:
    exp = dataclasses.replace(exp, variants=tuple(v for v in args.variants.split(",") if v))
  if args.seeds:
    exp = dataclasses.replace(exp, seeds=tuple(int(s) for s in args.seeds.split(",") if s))
  if args.steps:
    exp = dataclasses.replace(exp, train=dataclasses.replace(exp.train, max_steps=args.steps))
  selected_variants(exp)  # fail on a typo before any work
  summary = run(exp, Path(args.out), progress=not args.no_progress)
  print(markdown(summary))
  print(f"Total {summary['time_s']:.0f} s on {summary['cpu']}; wrote {Path(args.out) / 'summary.json'}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

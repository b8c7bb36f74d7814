"""Training on the toy problem (envs/toy_skills.py): its expert demonstrations in memory, and the
project's one training step on them, into an ordinary run directory.

The pipeline (`experiments.pipeline.job`) trains a config whose taskset is the toy's
(`loop.is_toy`) here instead of `loop.train`: the demonstrations are made in memory (a few
seconds; no dataset on disk), a jitted call runs `cfg.log_every` steps of
`loop.make_train_step` (one `lax.scan`, batches drawn on the device as ACT samples them), with
`loop.optimizer` and `loop.init_params`. The run directory is a run's like any other:
config.json with the run's record (`run_files`, so that few-shot reads its protocol from
the record), metrics.jsonl (losses and diag/ routing statistics), and the final checkpoint,
which `loop.load_params` reads. A run whose final checkpoint exists is not trained again; one
stopped before it trains from the start (minutes).

Demonstrations: `cfg.demos` per task of `cfg.data_taskset or cfg.taskset` (the unseen tasks'
few-shot dataset holds each of them), drawn from `cfg.data_seed` as the former toy driver drew
them (its published numbers used these demonstrations). Batches carry `skill_label`, read only
by loss.router_label: the primitive the expert was executing, or with
train.skill_labels=toy_targets the label mined from the demonstration (data/segments.py).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from envs import toy_skills as toy
from skillplug_jax.data import segments
from skillplug_jax.train.run_record import RunRecord
from skillplug_jax.train import checkpoint, loop, run_files
from skillplug_jax.train.config import TrainConfig
from skillplug_jax.train.scalars import ScalarLog

ENV = toy.ToySkillsConfig()  # the toy's physics and time limit (the evaluation's too: toy_rollout)


def demo_arrays(env: toy.ToySkillsConfig, key, tasks, per_task: int, chunk: int) -> dict:
  """Expert episodes as padded arrays: obs [E, T, ...], actions [E, T + chunk, 3] (the last
  action repeated past the end, masked in training), length [E], label [E, T] (the primitive),
  mined [E, T] (`segments.toy_targets`), task [E]."""
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


@functools.lru_cache(maxsize=8)
def demonstrations(taskset: str, demos: int, seed: int, chunk: int) -> dict:
  """`demos` expert episodes per task of a toy taskset (`toy.TASKSETS`), or of one toy task,
  from `seed`: the seen tasks from one key, each unseen task from its own (so that a task's
  few-shot demonstrations do not depend on which others are drawn)."""
  k_seen, k_unseen = jax.random.split(jax.random.PRNGKey(seed))
  if taskset == toy.TASKSET:
    return demo_arrays(ENV, k_seen, toy.SEEN, demos, chunk)
  tasks = [toy.TASK_IDS[n] for n in (toy.TASKSETS.get(taskset) or (taskset,))]
  if any(t in toy.SEEN for t in tasks):
    raise ValueError(f"toy taskset {taskset!r}: seen tasks are drawn together, as {toy.TASKSET!r}")
  parts = [demo_arrays(ENV, jax.random.fold_in(k_unseen, t), (t,), demos, chunk) for t in tasks]
  return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def data_of(cfg: TrainConfig) -> dict:
  """The demonstrations `cfg` trains on: its dataset's (`data_taskset`, else `taskset`), of its
  `taskset` alone (a few-shot fine-tune reads one task of the unseen tasks' dataset)."""
  data = demonstrations(cfg.data_taskset or cfg.taskset, cfg.demos, cfg.data_seed, cfg.model.chunk)
  wanted = [toy.TASK_IDS[n] for n in (toy.TASKSETS.get(cfg.taskset) or (cfg.taskset,))]
  keep = np.isin(data["task"], wanted)
  return {k: v[keep] for k, v in data.items()}


def sample_batch(data: dict, key, batch_size: int, chunk: int) -> dict:
  """ACT's sampling: a random episode, a random step of it, the chunk from there (masked past the end)."""
  k_ep, k_t = jax.random.split(key)
  ep = jax.random.randint(k_ep, (batch_size,), 0, data["length"].shape[0])
  length = data["length"][ep]
  t = jnp.floor(jax.random.uniform(k_t, (batch_size,)) * length).astype(jnp.int32)
  chunk_of = lambda a, s: jax.lax.dynamic_slice_in_dim(a, s, chunk, axis=0)  # noqa: E731
  batch = {"joint_pos": data["joint_pos"][ep, t], "object_state": data["object_state"][ep, t],
           "actions": jax.vmap(chunk_of)(data["actions"][ep], t),
           "action_mask": (t[:, None] + jnp.arange(chunk)[None]) < length[:, None],
           "task_id": data["task"][ep]}
  if "label" in data:  # the step's primitive or mined label, which only loss.router_label reads
    batch["skill_label"] = data["label"][ep, t]
  return batch


def _device_data(cfg: TrainConfig, data: dict) -> dict:
  labels = {"": "label", "toy_targets": "mined"}.get(cfg.skill_labels)
  if labels is None:
    raise ValueError(f"train.skill_labels={cfg.skill_labels!r}: the toy's labeller is 'toy_targets' "
                     "('': its ground-truth primitive)")
  out = {k: jnp.asarray(data[k]) for k in ("joint_pos", "object_state", "actions", "length", "task")}
  out["label"] = jnp.asarray(data[labels])
  return out


@functools.lru_cache(maxsize=16)
def _trainer(cfg: TrainConfig, steps: int):
  """(tx, a jitted (state, data, key) -> (state, mean metrics) running `steps` steps of `cfg`).

  Cached per config less its seed and run directory (they arrive in `key` and are not read),
  so seeds, variants' runs of one config and few-shot tasks share the compile."""
  like = jax.eval_shape(lambda: loop.init_params(cfg, jax.random.PRNGKey(0)))
  tx = loop.optimizer(cfg, like, cfg.num_steps(1))

  @jax.jit
  def run(state, data, key):
    data_key, step_key = jax.random.split(key)
    train_step = loop.make_train_step(cfg, tx, step_key)

    def body(state, _):
      batch = sample_batch(data, jax.random.fold_in(data_key, state.step), cfg.batch_size, cfg.model.chunk)
      return train_step(state, batch)

    state, metrics = jax.lax.scan(body, state, None, length=steps)
    return state, jax.tree.map(jnp.mean, metrics)

  return tx, run


def _shared(cfg: TrainConfig) -> TrainConfig:
  """`cfg` less what does not change the computation (the compile cache's key): a few-shot
  fine-tune's task is in its data, not its program, so the unseen tasks share one compile."""
  return dataclasses.replace(cfg, seed=0, workdir="", init_from="", taskset=cfg.data_taskset or cfg.taskset)


@functools.lru_cache(maxsize=16)
def _init(cfg: TrainConfig):
  """`loop.init_params` of `cfg`, jitted (eagerly, each of its operations would compile alone)."""
  return jax.jit(lambda key: loop.init_params(cfg, key))


def train(cfg: TrainConfig, progress: bool = True, record: RunRecord | None = None) -> Path:
  """Train `cfg` (from `cfg.init_from`'s parameters when set, its groups `cfg.trainable` alone)
  into `cfg.run_dir`; return it. A run whose final checkpoint exists is kept as it is."""
  if cfg.max_steps <= 0:
    raise ValueError(f"the toy trains by steps: train.max_steps must be > 0 (got {cfg.max_steps})")
  run_dir, total = cfg.run_dir, cfg.max_steps
  with loop.writer_lock(run_dir):
    mngr, _ = checkpoint.manager_for_training(run_dir, cfg.keep_checkpoints)
    try:
      if mngr.latest_step() == total:
        run_files.check_resumable(run_dir, cfg)
        return run_dir
      data = data_of(cfg)
      init_key, step_key = jax.random.split(jax.random.PRNGKey(cfg.seed))
      if cfg.init_from:  # few-shot: start from a multi-task run's parameters
        params = loop.params_from_source(cfg, _init(_shared(cfg))(init_key))
      else:
        params = _init(_shared(cfg))(init_key)
      if (run_dir / run_files.CONFIG_FILE).exists():  # restarted: it keeps the record it started with
        record = run_files.stored_record(run_dir) or record
      run_files.write_run_files(run_dir, cfg, {}, record)  # no normalisation: the toy's inputs are raw
      device_data = _device_data(cfg, data)
      tx, _ = _trainer(_shared(cfg), min(cfg.log_every, total))
      state = loop.TrainState(jnp.zeros((), jnp.int32), params, tx.init(params))
      log = ScalarLog(run_dir)
      try:
        while int(state.step) < total:
          steps = min(cfg.log_every, total - int(state.step))
          _, run = _trainer(_shared(cfg), steps)
          state, metrics = jax.block_until_ready(run(state, device_data, step_key))
          means = {k: float(v) for k, v in jax.device_get(metrics).items()}
          if not all(math.isfinite(v) for v in means.values()):
            raise loop.TrainingError(f"non-finite loss before step {int(state.step)}: {means}")
          log.write(int(state.step), {(f"diag/{k[5:]}" if k.startswith("diag_") else f"loss/{k}"): v
                                      for k, v in means.items() if k != "grad_norm"}
                    | {"train/grad_norm": means["grad_norm"]})
      finally:
        log.close()
      checkpoint.save(mngr, total, state)
      mngr.wait_until_finished()
    finally:
      mngr.close()
  if progress:
    print(f"run {run_dir}: {total} steps, last loss {means['loss']:.4f}", file=sys.stderr)
  return run_dir

"""The training loop, top to bottom: data, model, optimiser, checkpoints, steps.

One process drives every local device: parameters are replicated, the batch
is split over a 1-D 'data' mesh, and XLA inserts the gradient all-reduce
(several hosts: call `jax.distributed.initialize()` first; the mesh then
spans every process's devices). A step's randomness is fold_in(seed, step)
and the loader's batch is a function of (seed, step), so a run resumed from
its last checkpoint continues exactly as if it had not been stopped. A damaged
last checkpoint is set aside, with a warning, and the run resumes from the
newest intact one. A run directory has one writer: a second process training
into it stops at once, naming the first (`dir_lock`). SIGTERM or SIGINT
checkpoints the step under way and raises `preemption.Preempted`: the same
command resumes from it, bit for bit.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import signal
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

import envs
from skillplug_jax import dir_lock, losses
from skillplug_jax.data import demos as demo_data
from skillplug_jax.data import loader as data_loader
from skillplug_jax.data import language, segments
from skillplug_jax.model import config as model_config
from skillplug_jax.model import freeze
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import checkpoint, preemption, run_files
from skillplug_jax.train.config import TrainConfig
from skillplug_jax.train.run_record import RunRecord
from skillplug_jax.train.scalars import ScalarLog


class TrainState(NamedTuple):
  step: jax.Array
  params: Any
  opt_state: Any


class TrainingError(RuntimeError):
  """Training cannot go on (non-finite loss); checkpoints already written are kept."""


def dataset_config(cfg: TrainConfig) -> demo_data.DemoConfig:
  return demo_data.DemoConfig(taskset=cfg.data_taskset or cfg.taskset, demos=cfg.demos,
                              images=cfg.model.use_images, image_size=cfg.model.image_size, seed=cfg.data_seed,
                              backend=cfg.backend)


def load_data(cfg: TrainConfig, generate: bool = True, progress: bool = True) -> data_loader.Demonstrations:
  """The run's demonstrations; generated first when missing and `generate`."""
  dcfg = dataset_config(cfg)
  path = demo_data.dataset_path(dcfg, cfg.data_dir)
  if not path.exists() and generate:
    demo_data.make_demos(dcfg, cfg.data_dir, progress=progress)
  tasks = tuple(n for part in cfg.taskset.split(",") for n in envs.taskset(part))
  return data_loader.load_demonstrations(path, tasks=tasks, images=cfg.model.use_images,
                                         image_size=cfg.model.image_size)


def learning_rate(cfg: TrainConfig, total_steps: int) -> optax.Schedule:
  """Linear warm-up, then constant or a cosine decay to 0 at `total_steps`."""
  warmup = max(cfg.warmup_steps, 0)
  if cfg.lr_schedule == "cosine":
    return optax.warmup_cosine_decay_schedule(0.0, cfg.lr, warmup, max(total_steps, warmup + 1))
  if warmup == 0:
    return optax.constant_schedule(cfg.lr)
  return optax.join_schedules(
      [optax.linear_schedule(0.0, cfg.lr, warmup), optax.constant_schedule(cfg.lr)], [warmup])


def optimizer(cfg: TrainConfig, params, total_steps: int) -> optax.GradientTransformation:
  """AdamW after global-norm clipping; frozen groups get zero updates (optax mask)."""
  tx = optax.adamw(learning_rate(cfg, total_steps), weight_decay=cfg.weight_decay)
  if cfg.grad_clip > 0:
    tx = optax.chain(optax.clip_by_global_norm(cfg.grad_clip), tx)
  if cfg.trainable:
    tx = freeze.masked_optimizer(tx, params, cfg.trainable)
  return tx


def is_toy(cfg: TrainConfig) -> bool:
  """Whether `cfg` trains on the toy problem (envs/toy_skills.py: its demonstrations are made in
  memory, `train.toy`) rather than on a tabletop dataset."""
  from envs import toy_skills
  return (cfg.data_taskset or cfg.taskset) in toy_skills.TASKSETS or cfg.taskset in toy_skills.TASK_IDS


def is_libero(cfg: TrainConfig) -> bool:
  """Whether `cfg` trains on LIBERO demonstrations (their layout: envs/libero/layout.py)."""
  from envs.libero import suites as libero_suites
  return libero_suites.is_libero((cfg.data_taskset or cfg.taskset).split(",")[0])


def object_state_dim(cfg: TrainConfig) -> int:
  """The width of `cfg`'s object_state: the toy's, LIBERO's, or the tabletop tasks' (envs.OBJECT_STATE_DIM)."""
  from envs import toy_skills
  from envs.libero import layout as libero_layout
  if is_toy(cfg):
    return toy_skills.OBJECT_STATE_DIM
  return libero_layout.OBJECT_STATE_DIM if is_libero(cfg) else envs.OBJECT_STATE_DIM


def example_batch(cfg: TrainConfig, batch_size: int) -> dict:
  """A batch of zeros shaped like `cfg`'s (the observation shapes follow its taskset)."""
  m = cfg.model
  proprio = ({"joint_pos": m.joint_dim} if m.proprio == ("joint_pos",)
             else {k: model_config.PROPRIO_WIDTHS[k] for k in m.proprio})
  b = {**{k: jnp.zeros((batch_size, w)) for k, w in proprio.items()},
       "object_state": jnp.zeros((batch_size, object_state_dim(cfg))),
       "actions": jnp.zeros((batch_size, m.chunk, m.action_dim)),
       "action_mask": jnp.ones((batch_size, m.chunk), bool),
       "task_id": jnp.zeros((batch_size,), jnp.int32)}
  if m.use_images:
    for cam in m.cameras:
      b[f"{cam}_rgb"] = jnp.zeros((batch_size, *m.image_size, 3), jnp.uint8)
  if m.instruction_vocab:
    b["instruction"] = jnp.zeros((batch_size, m.instruction_words), jnp.int32)
  return b


def init_params(cfg: TrainConfig, key: jax.Array):
  k_params, k_drop, k_sample = jax.random.split(key, 3)
  variables = Policy(cfg.model).init({"params": k_params, "dropout": k_drop, "sample": k_sample},
                                     example_batch(cfg, 2), train=True)
  return variables["params"]


def make_train_step(cfg: TrainConfig, tx: optax.GradientTransformation, key: jax.Array):
  policy = Policy(cfg.model)

  def loss_fn(params, batch, step):
    k = jax.random.fold_in(key, step)
    k_drop, k_sample = jax.random.split(k)
    out = policy.apply({"params": params}, batch, train=True, rngs={"dropout": k_drop, "sample": k_sample})
    return losses.total_loss(out, batch, cfg.loss)

  def train_step(state: TrainState, batch):
    (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params, batch, state.step)
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    metrics["grad_norm"] = optax.tree.norm(grads)
    return TrainState(state.step + 1, params, opt_state), metrics

  return train_step


def params_from_source(cfg: TrainConfig, params):
  """A fine-tune's starting parameters: its source run's (`cfg.init_from`), plus `params`' (its own
  initialisation) for the groups a fine-tune may add (`model.config.FINE_TUNE_ADDITIONS`: the
  adapter). Any other difference between the two models is an error that names it."""
  src_cfg = run_files.read_config(cfg.init_from)
  diffs = [d for d in run_files.config_differences(src_cfg.model, cfg.model)
           if not _fine_tune_addition(d, src_cfg.model)]
  if diffs:
    raise checkpoint.CheckpointError(f"{cfg.init_from} has a different model: {'; '.join(diffs)}")
  groups = jax.eval_shape(lambda: init_params(src_cfg, jax.random.PRNGKey(0))).keys()
  _, loaded, _ = load_params(cfg.init_from, like={k: v for k, v in params.items() if k in groups})
  return {**params, **loaded}


def _fine_tune_addition(diff: str, source) -> bool:
  """Whether a `config_differences` line is a change a fine-tune may make to its source's model."""
  name = diff.split(":")[0]
  if name not in model_config.FINE_TUNE_ADDITIONS:
    return False
  value = source
  for part in name.split("."):
    value = getattr(value, part)
  return value == model_config.FINE_TUNE_ADDITIONS[name]


def load_params(run_dir: str | Path, like=None):
  """(cfg, params, step) of a run's latest checkpoint (shapes checked against `like` if given).

  Only the parameters are read (no optimiser is built), and a damaged latest
  checkpoint is an error that names it, not an older result.
  """
  run_dir = Path(run_dir)
  cfg = run_files.read_config(run_dir)
  if like is None:
    like = jax.eval_shape(lambda: init_params(cfg, jax.random.PRNGKey(0)))
  params, step = checkpoint.restore_params(run_dir, like)
  return cfg, params, step


def train(cfg: TrainConfig, progress: bool = True, stop_after: int | None = None,
          record: RunRecord | None = None) -> Path:
  """Train (or resume) `cfg`; return the run directory.

  record: what the run keeps of its experiment config (`experiment.record`), to
  name its table row and adapt it later; a resumed run keeps the one it started
  with. stop_after: return after this many steps of this call, as a kill would
  (tests use it to check that resuming is exact). The training API's edge: a
  `cfg.backend` of "auto" is resolved here, once, and the run records the result.
  """
  cfg = dataclasses.replace(cfg, backend=envs.resolve_backend(cfg.backend))
  with writer_lock(cfg.run_dir):
    return _train(cfg, progress, stop_after, record)


def skill_labels(cfg: TrainConfig, data) -> np.ndarray | None:
  """Every step's label from `cfg.skill_labels`' labeller (data/segments.py), or None."""
  if not cfg.skill_labels:
    return None
  s = data.steps
  action = s["action"]
  if is_libero(cfg):  # LIBERO's gripper command is +-1; the labellers read our tabletop's opening
    from envs.libero import layout as libero_layout
    action = libero_layout.tabletop_gripper(action)
  return segments.label_steps(cfg.skill_labels, s["joint_pos"], s["object_state"], action,
                              data.start, data.length)


def instruction_ids(cfg: TrainConfig, data: data_loader.Demonstrations):
  """(data with its statistics holding the vocabulary, [tasks, words] word ids) for a model that
  reads instructions; (data, None) for one that does not. The vocabulary is the source run's for a
  fine-tune (its embeddings were learned for it), else the installed benchmark's (data/language.py)."""
  m = cfg.model
  if not m.instruction_vocab:
    return data, None
  if not data.language:
    raise ValueError(f"model.instruction_vocab={m.instruction_vocab}: the model reads task instructions, and "
                     f"the dataset {data.path} has none (our DISCOVERSE datasets come without language)")
  vocab = tuple(data.stats.get(language.VOCABULARY_KEY) or language.benchmark_vocabulary())
  if len(vocab) > m.instruction_vocab:
    raise ValueError(f"model.instruction_vocab={m.instruction_vocab} rows cannot hold the vocabulary's "
                     f"{len(vocab)} words (reserved ids included)")
  stats = {**data.stats, language.VOCABULARY_KEY: list(vocab)}
  return dataclasses.replace(data, stats=stats), language.encode(data.language, vocab, m.instruction_words)


def writer_lock(run_dir: Path):
  """The run directory's lock (`dir_lock`): a second process training into it stops at once. Several
  hosts (jax.distributed) write one run together: the first process holds it for them."""
  if jax.process_index() != 0:
    return contextlib.nullcontext()
  return dir_lock.DirLock(run_dir, what=f"run directory {run_dir}")


def _train(cfg: TrainConfig, progress: bool, stop_after: int | None, record: RunRecord | None) -> Path:
  run_dir = cfg.run_dir
  data = load_data(cfg, progress=progress)
  if cfg.init_from:  # the frozen encoder expects the inputs normalised as in its own training
    data = dataclasses.replace(data, stats=run_files.read_stats(cfg.init_from))
  data, instructions = instruction_ids(cfg, data)
  n_dev = jax.device_count()
  mesh = Mesh(np.asarray(jax.devices()), ("data",))
  replicated = NamedSharding(mesh, PartitionSpec())
  loader = data_loader.ChunkLoader(data, cfg.batch_size, chunk=cfg.model.chunk, seed=cfg.seed,
                                   images=cfg.model.use_images,
                                   sharding=NamedSharding(mesh, PartitionSpec("data")),
                                   normalize_object_state=cfg.model.normalize_object_state,
                                   skill_labels=skill_labels(cfg, data), instructions=instructions)
  total = cfg.num_steps(data.num_episodes)

  key = jax.random.PRNGKey(cfg.seed)
  init_key, step_key = jax.random.split(key)
  params = init_params(cfg, init_key)
  if cfg.init_from:  # few-shot: start from a multi-task run's parameters
    params = params_from_source(cfg, params)
  tx = optimizer(cfg, params, total)
  state = TrainState(jnp.zeros((), jnp.int32), params, tx.init(params))
  state = jax.device_put(state, replicated)

  mngr, moved = checkpoint.manager_for_training(run_dir, cfg.keep_checkpoints)  # unreadable step metadata
  start = 0
  if mngr.latest_step() is not None:
    run_files.check_resumable(run_dir, cfg)
    record = run_files.stored_record(run_dir) or record  # the record it started with
    state, start, damaged = checkpoint.restore_latest(mngr, state, fallback=True)
    # set aside, or orbax would skip saving their steps again
    moved += [(bad, checkpoint.set_aside(mngr, bad, run_dir)) for bad in damaged]
  for bad, where in moved:
    print(f"warning: {bad}; moved it to {where} and "
          + (f"resuming from checkpoint {start}" if start else "training from the start"), file=sys.stderr)
  run_files.write_run_files(run_dir, cfg, data.stats, record)

  step_fn = jax.jit(make_train_step(cfg, tx, step_key), donate_argnums=0,
                    out_shardings=(replicated, replicated))
  log = ScalarLog(run_dir, resume_step=start)
  end = total if stop_after is None else min(total, start + stop_after)
  bar = tqdm(total=total, initial=start, desc=f"train {cfg.model.policy}", unit="step", file=sys.stderr,
             disable=not progress, dynamic_ncols=True)
  window, t_window, wait0, last_loss = [], time.perf_counter(), loader.wait_s, math.nan
  stop = preemption.StopRequests()  # SIGTERM/SIGINT: finish this step, checkpoint it, stop
  try:
    with stop:
      for step, batch in zip(range(start, end), loader.iterate(start_step=start, num_steps=end - start)):
        state, metrics = step_fn(state, batch)
        window.append(metrics)
        done = step + 1
        stopping = stop.agreed()
        if done % cfg.log_every == 0 or done == end or done % cfg.ckpt_every == 0 or stopping:
          host = jax.device_get(window)  # one transfer for the whole window
          means = {k: float(np.mean([m[k] for m in host])) for k in host[0]}
          if not all(math.isfinite(v) for v in means.values()):
            bad = {k: v for k, v in means.items() if not math.isfinite(v)}
            raise TrainingError(
                f"non-finite loss between steps {done - len(window)} and {done}: {bad}; the last good "
                f"checkpoint (step {mngr.latest_step()}) in {run_dir / 'checkpoints'} is kept")
          dt = time.perf_counter() - t_window
          scalars = {(f"diag/{k[5:]}" if k.startswith("diag_") else f"loss/{k}"): v
                     for k, v in means.items() if k != "grad_norm"}
          scalars.update({"train/grad_norm": means["grad_norm"],
                          "train/epoch": done * cfg.batch_size / data.num_episodes,
                          "train/steps_per_s": len(window) / dt,
                          "train/data_wait_frac": (loader.wait_s - wait0) / dt})
          log.write(done, scalars)
          last_loss = means["loss"]
          bar.set_postfix(loss=f"{last_loss:.4f}", epoch=f"{scalars['train/epoch']:.1f}")
          window, t_window, wait0 = [], time.perf_counter(), loader.wait_s
        if done % cfg.ckpt_every == 0 or done == total or stopping:
          checkpoint.save(mngr, done, state)
        bar.update(1)
        if stopping:
          mngr.wait_until_finished()
          raise preemption.Preempted(stop.signum or signal.SIGTERM, done, run_dir)
  finally:
    bar.close()
    log.close()
    mngr.wait_until_finished()
    mngr.close()
  if progress:
    print(f"run {run_dir}: step {int(state.step)}/{total} on {n_dev} device(s), last loss {last_loss:.4f}; "
          f"checkpoints in {run_dir / 'checkpoints'}", file=sys.stderr)
  return run_dir

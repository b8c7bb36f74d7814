"""Synthetic demonstration datasets for tests: random episodes written like `make_demos` writes."""

import dataclasses
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import envs
from skillplug_jax.data import normalization, rlds
from skillplug_jax.data.demos import DemoConfig
from skillplug_jax.data.recording import Episode

D = envs.OBJECT_STATE_DIM


def synthetic_episode(rng, length, images=None, success=True):
  obs = {"joint_pos": rng.normal(size=(length, 7)).astype(np.float32),
         "object_state": rng.normal(size=(length, D)).astype(np.float32)}
  if images is not None:
    h, w = images
    for cam in ("side", "wrist"):
      obs[f"{cam}_rgb"] = rng.integers(0, 256, size=(length, h, w, 3), dtype=np.uint8)
  return Episode(observation=obs, action=rng.normal(size=(length, 7)).astype(np.float32),
                 success=success, nan=False)


def write_synthetic(root: Path, name: str, spec: rlds.DatasetSpec, records: list, stats=True) -> Path:
  """Write records the way `make_demos` does (build, stats, rename)."""
  version_dir = rlds.write_dataset(root / f".{name}.building", spec, lambda: records, {"test": True})
  if stats:
    normalization.write_stats(version_dir, normalization.compute_stats(r.episode for r in records))
  rlds.write_checksums(version_dir)
  final = root / name
  os.replace(version_dir, final)
  return final


def write_two_task_demos(root: Path, rng, tasks=("jujube_pick", "kiwi_place")) -> None:
  """3 random state-only episodes per task, where a `demos=3` training run on `tasks` looks."""
  records = [rlds.EpisodeRecord(task, 0, i, synthetic_episode(rng, int(rng.integers(8, 40))))
             for task in tasks for i in range(3)]
  write_synthetic(root, state_dataset_name(",".join(tasks)), rlds.DatasetSpec(tuple(tasks), None), records)


def state_dataset_name(taskset: str, demos: int = 3) -> str:
  """Where a state-only training run with `demos` per task looks for its dataset (its name holds
  the backend: these synthetic episodes stand in for the C engine's, `auto` on a CPU)."""
  return DemoConfig(taskset=taskset, demos=demos, images=False, backend="mujoco").name


# ---- a model's inputs, for the model and switch tests ------------------------------
MODEL_BATCH = 2


def model_config(base, **kw):
  """`base` (a ModelConfig) with `kw` replaced; PlugConfig's fields may be given flat (num_skills=3)."""
  from skillplug_jax.model.plug import PlugConfig
  plug_fields = {f.name for f in dataclasses.fields(PlugConfig)}
  plug = {k: kw.pop(k) for k in list(kw) if k in plug_fields}
  return dataclasses.replace(base, **kw, plug=dataclasses.replace(base.plug, **plug))


def model_batch(cfg, seed: int = 0):
  """A training batch of MODEL_BATCH random samples for `cfg` (a ModelConfig); the second
  sample's episode ends after 2 steps."""
  rng = np.random.default_rng(seed)
  batch = dict(
      joint_pos=rng.normal(size=(MODEL_BATCH, cfg.joint_dim)).astype(np.float32),
      object_state=rng.normal(size=(MODEL_BATCH, D)).astype(np.float32),
      actions=rng.normal(size=(MODEL_BATCH, cfg.chunk, cfg.action_dim)).astype(np.float32),
      action_mask=np.arange(cfg.chunk)[None] < np.array([cfg.chunk, 2])[:, None],
      task_id=np.arange(MODEL_BATCH, dtype=np.int32))
  if cfg.use_images:
    for cam in cfg.cameras:
      batch[f"{cam}_rgb"] = rng.integers(0, 256, (MODEL_BATCH, *cfg.image_size, 3), dtype=np.uint8)
  return jax.tree.map(jnp.asarray, batch)


def rngs(seed: int = 0) -> dict:
  """The training pass's rngs ('dropout', 'sample') from one seed."""
  k1, k2 = jax.random.split(jax.random.key(seed))
  return {"dropout": k1, "sample": k2}

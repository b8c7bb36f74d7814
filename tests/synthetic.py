"""Synthetic demonstration datasets for tests: random episodes written like `make_demos` writes."""

import os
from pathlib import Path

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

"""Run directories: orbax checkpoints plus the JSON a policy needs to be rebuilt.

    <run>/config.json       the TrainConfig (model, losses, data, optimiser)
    <run>/norm_stats.json   the dataset's action / joint-position statistics
    <run>/checkpoints/<step>/  orbax: params, opt_state, step

Orbax writes each checkpoint into a temporary directory and renames it when
complete, so a run killed mid-save keeps its previous checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from skillplug_jax.atomic_json import write_json_atomic
from skillplug_jax.train import config as train_config

CONFIG_FILE = "config.json"
STATS_FILE = "norm_stats.json"

# Settings a resumed run may change without invalidating its checkpoints.
RESUMABLE_CHANGES = {"workdir", "log_every", "ckpt_every", "keep_checkpoints", "max_steps", "epochs",
                     "data_dir"}


class CheckpointError(ValueError):
  """A checkpoint is missing or was made by an incompatible configuration."""


def manager(run_dir: Path, keep: int = 2) -> ocp.CheckpointManager:
  return ocp.CheckpointManager(
      (Path(run_dir) / "checkpoints").absolute(),
      options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True))


def save(mngr: ocp.CheckpointManager, step: int, state) -> None:
  mngr.save(step, args=ocp.args.StandardSave(state))


def restore(mngr: ocp.CheckpointManager, step: int, like):
  """Restore into the structure, shapes and shardings of `like`."""
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
  try:
    return mngr.restore(step, args=ocp.args.StandardRestore(abstract))
  except (ValueError, KeyError, TypeError) as e:
    raise CheckpointError(f"checkpoint {step} in {mngr.directory} does not fit this model: {e}") from e


def write_run_files(run_dir: Path, cfg, stats: dict) -> None:
  run_dir.mkdir(parents=True, exist_ok=True)
  write_json_atomic(run_dir / CONFIG_FILE, train_config.to_dict(cfg))
  write_json_atomic(run_dir / STATS_FILE, stats)


def read_config(run_dir: Path) -> train_config.TrainConfig:
  path = Path(run_dir) / CONFIG_FILE
  if not path.exists():
    raise CheckpointError(f"no training run at {run_dir} ({CONFIG_FILE} is missing)")
  try:
    return train_config.from_dict(json.loads(path.read_text()))
  except (ValueError, TypeError, KeyError) as e:
    raise CheckpointError(f"{path} is not a readable training config: {e}") from e


def read_stats(run_dir: Path) -> dict:
  path = Path(run_dir) / STATS_FILE
  if not path.exists():
    raise CheckpointError(f"{run_dir} has no {STATS_FILE}")
  return json.loads(path.read_text())


def config_differences(old, new, prefix: str = "") -> list[str]:
  """Fields (dotted) whose values differ between two configs."""
  diffs = []
  for f in dataclasses.fields(old):
    a, b = getattr(old, f.name), getattr(new, f.name)
    if dataclasses.is_dataclass(a):
      diffs += config_differences(a, b, prefix + f.name + ".")
    elif a != b:
      diffs.append(f"{prefix}{f.name}: {a!r} -> {b!r}")
  return diffs


def check_resumable(run_dir: Path, cfg) -> None:
  old = read_config(run_dir)
  diffs = [d for d in config_differences(old, cfg) if d.split(":")[0] not in RESUMABLE_CHANGES]
  if diffs:
    raise CheckpointError(
        f"{run_dir} holds checkpoints of a different configuration; use another --workdir or "
        f"delete it. Differences: {'; '.join(diffs)}")

"""A run directory's JSON: what rebuilds its policy, and what names and adapts it.

    <run>/config.json       the TrainConfig (model, losses, data, optimiser), and under
                            "experiment" the run's record of its experiment config
                            (`run_record.RunRecord`: config name, few-shot protocol, the
                            config's training settings its overrides are read against)
    <run>/norm_stats.json   the dataset's action / joint-position / object-state statistics

The record is written when the run starts and kept when it resumes, so a config
file edited later does not rename the run's table row or change how it is adapted.
Runs from before the record load as before (`stored_record` is None); their record
is rebuilt from today's config file, with a warning (`experiment.read_record`).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax

from skillplug_jax.atomic_json import write_json_atomic
from skillplug_jax.train import config as train_config
from skillplug_jax.train import run_record
from skillplug_jax.train.checkpoint import CheckpointError

CONFIG_FILE = "config.json"
STATS_FILE = "norm_stats.json"
RECORD_KEY = "experiment"  # config.json's entry beside the TrainConfig's fields

# Settings a resumed run may change without invalidating its checkpoints.
RESUMABLE_CHANGES = {"workdir", "log_every", "ckpt_every", "keep_checkpoints", "max_steps", "epochs",
                     "data_dir"}


def write_run_files(run_dir: Path, cfg, stats: dict, record: run_record.RunRecord | None = None) -> None:
  """config.json (with `record`, when given) and norm_stats.json, each written atomically; of
  several processes training one run (jax.distributed), the first writes them."""
  if jax.process_index() != 0:
    return
  run_dir.mkdir(parents=True, exist_ok=True)
  payload = train_config.to_dict(cfg)
  if record is not None:
    payload[RECORD_KEY] = run_record.record_to_dict(record)
  write_json_atomic(run_dir / CONFIG_FILE, payload)
  write_json_atomic(run_dir / STATS_FILE, stats)


def _read_json(run_dir: Path) -> dict:
  path = Path(run_dir) / CONFIG_FILE
  if not path.exists():
    raise CheckpointError(f"no training run at {run_dir} ({CONFIG_FILE} is missing)")
  try:
    return json.loads(path.read_text())
  except ValueError as e:
    raise CheckpointError(f"{path} is not a readable training config: {e}") from e


def read_config(run_dir: Path) -> train_config.TrainConfig:
  d = _read_json(run_dir)
  d.pop(RECORD_KEY, None)
  try:
    return train_config.from_dict(d)
  except (ValueError, TypeError, KeyError) as e:
    raise CheckpointError(f"{Path(run_dir) / CONFIG_FILE} is not a readable training config: {e}") from e


def stored_record(run_dir: Path) -> run_record.RunRecord | None:
  """The record the run keeps in its config.json; None for a run from before runs kept one."""
  d = _read_json(run_dir).get(RECORD_KEY)
  if d is None:
    return None
  try:
    return run_record.record_from_dict(d)
  except (ValueError, TypeError, KeyError) as e:
    raise CheckpointError(f"{Path(run_dir) / CONFIG_FILE}: its '{RECORD_KEY}' entry is not a readable "
                          f"record: {e}") from e


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

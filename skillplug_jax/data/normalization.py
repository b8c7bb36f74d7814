"""Action and joint-position normalisation statistics, stored beside the dataset.

As in ACT: z-score with the standard deviation clipped from below, so a
joint the experts never move (or the gripper in a push task) does not blow up.
The statistics are computed once, when the dataset is written, and travel
with checkpoints so a policy un-normalises its actions the same way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from skillplug_jax.atomic_json import read_json, write_json_atomic
from skillplug_jax.data import rlds

STATS_FILE = "norm_stats.json"
MIN_STD = 1e-2
KEYS = ("action", "joint_pos")


def compute_stats(episodes: Iterable) -> dict:
  """Mean and clipped std over every step of every episode (recording.Episode)."""
  action, joint = [], []
  for ep in episodes:
    action.append(ep.action)
    joint.append(ep.observation["joint_pos"])
  return stats_of(np.concatenate(action), np.concatenate(joint))


def stats_of(action: np.ndarray, joint_pos: np.ndarray) -> dict:
  out = {}
  for name, x in (("action", action), ("joint_pos", joint_pos)):
    x = np.asarray(x, np.float64)
    out[name] = {"mean": x.mean(0).tolist(), "std": np.maximum(x.std(0), MIN_STD).tolist(),
                 "min": x.min(0).tolist(), "max": x.max(0).tolist()}
  out["num_steps"] = int(len(action))
  return out


def write_stats(dataset_dir: str | Path, stats: dict) -> None:
  write_json_atomic(Path(dataset_dir) / STATS_FILE, stats)


def read_stats(dataset_dir: str | Path) -> dict | None:
  path = Path(dataset_dir) / STATS_FILE
  if not path.exists():
    return None
  try:
    stats = read_json(path)
    for k in KEYS:
      if len(stats[k]["mean"]) != rlds.ACTION_DIM or len(stats[k]["std"]) != rlds.ACTION_DIM:
        raise ValueError(f"{k} statistics have the wrong length")
  except (ValueError, KeyError, TypeError) as e:
    raise rlds.DatasetError(f"{path} is corrupt ({e}); delete it to recompute") from e
  return stats


def normalize(x, stats: dict, key: str):
  return (x - np.asarray(stats[key]["mean"], np.float32)) / np.asarray(stats[key]["std"], np.float32)


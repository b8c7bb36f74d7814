"""Normalisation statistics of actions, joint and object state, stored beside the dataset.

As in ACT: z-score with the standard deviation clipped from below, so a
joint the experts never move (or the gripper in a push task) does not blow up.
The statistics are computed once, when the dataset is written, and travel
with checkpoints so a policy normalises its inputs and un-normalises its
actions the same way. Object state (ACT's sim tasks had none) is normalised
per padded dimension over every task of the dataset; `ModelConfig.
normalize_object_state` says whether a policy reads it normalised. Datasets
written before it was recorded get it computed at load time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from envs import OBJECT_STATE_DIM
from skillplug_jax.atomic_json import read_json, write_json_atomic
from skillplug_jax.data import rlds

STATS_FILE = "norm_stats.json"
MIN_STD = 1e-2
KEYS = ("action", "joint_pos")
WIDTH = {"action": rlds.ACTION_DIM, "joint_pos": rlds.ACTION_DIM, "object_state": OBJECT_STATE_DIM}


def compute_stats(episodes: Iterable) -> dict:
  """Mean and clipped std over every step of every episode (recording.Episode)."""
  action, joint, obj = [], [], []
  for ep in episodes:
    action.append(ep.action)
    joint.append(ep.observation["joint_pos"])
    obj.append(ep.observation["object_state"])
  return stats_of(np.concatenate(action), np.concatenate(joint), np.concatenate(obj))


def moments(x: np.ndarray) -> dict:
  x = np.asarray(x, np.float64)
  return {"mean": x.mean(0).tolist(), "std": np.maximum(x.std(0), MIN_STD).tolist(),
          "min": x.min(0).tolist(), "max": x.max(0).tolist()}


def stats_of(action: np.ndarray, joint_pos: np.ndarray, object_state: np.ndarray | None = None,
             **state: np.ndarray) -> dict:
  """Moments of the actions and of each low-dim observation field (a layout's other
  proprioception, e.g. LIBERO's gripper_qpos, eef_pos and eef_quat, by name)."""
  out = {"action": moments(action), "joint_pos": moments(joint_pos)}
  if object_state is not None:
    out["object_state"] = moments(object_state)
  out.update({k: moments(v) for k, v in state.items()})
  out["num_steps"] = int(len(action))
  return out


def write_stats(dataset_dir: str | Path, stats: dict) -> None:
  write_json_atomic(Path(dataset_dir) / STATS_FILE, stats)


def read_stats(dataset_dir: str | Path, widths: dict | None = None) -> dict | None:
  """The dataset's statistics, checked against the widths of the action and its layout's fields
  (`widths`, default DISCOVERSE's); None when there are none."""
  widths = WIDTH if widths is None else widths
  path = Path(dataset_dir) / STATS_FILE
  if not path.exists():
    return None
  try:
    stats = read_json(path)
    for k in KEYS + tuple(k for k in widths if k in stats and k not in KEYS):
      if len(stats[k]["mean"]) != widths[k] or len(stats[k]["std"]) != widths[k]:
        raise ValueError(f"{k} statistics have the wrong length")
  except (ValueError, KeyError, TypeError) as e:
    raise rlds.DatasetError(f"{path} is corrupt ({e}); delete it to recompute") from e
  return stats


def normalize(x, stats: dict, key: str):
  return (x - np.asarray(stats[key]["mean"], np.float32)) / np.asarray(stats[key]["std"], np.float32)


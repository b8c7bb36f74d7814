"""Rows of the result tables: runs grouped by what was trained, never by label alone.

A run's training key is its whole `TrainConfig` (dotted names) less the
settings that say where or how often, not what, is trained: the seed (the
replicate axis: the seeds of one key are one row, mean ± SE), the run,
data and source directories, and the logging / checkpoint cadence. So
evaluating K=2 and K=4 runs together gives two rows, and three seeds of one
configuration give one.

A row's name is the policy label plus what tells it apart from the other
rows: the preset when presets differ, and each setting overridden (against
its preset) in some row whose value is not the same in every row, e.g.
`ACT+SkillPlug (num_skills=2)`. Settings ACT does not read (skills, the
SkillPlug loss terms) are left out of ACT rows' names.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any, Mapping, Sequence

from skillplug_jax.train import config as train_config

# Where and how often, not what: two runs differing only in these trained the same thing.
NOT_TRAINING = frozenset({"seed", "workdir", "data_dir", "init_from", "log_every", "ckpt_every",
                          "keep_checkpoints"})
# Settings only ACT+SkillPlug reads: an ACT row's name never mentions them.
SKILLPLUG_ONLY = frozenset({"model.num_skills", "model.skill_latent_dim", "model.alignment_dim",
                            "model.interactor", "model.router_temperature", "loss.kl", "loss.bsa",
                            "loss.sd"})


def policy_label(cfg: train_config.TrainConfig) -> str:
  return _label({"model.policy": cfg.model.policy})


def _label(key: Mapping[str, Any]) -> str:
  return "ACT+SkillPlug" if key["model.policy"] == "skillplug" else "ACT"


def key_id(key: Mapping[str, Any]) -> str:
  """A training key as one comparable string (the JSON keeps the key itself)."""
  return json.dumps(key, sort_keys=True)


def _flat(d: Mapping[str, Any], prefix: str = "") -> dict:
  out = {}
  for k, v in d.items():
    if isinstance(v, Mapping):
      out.update(_flat(v, f"{prefix}{k}."))
    else:
      out[prefix + k] = list(v) if isinstance(v, tuple) else v  # as JSON reads it back
  return out


def training_key(cfg: train_config.TrainConfig) -> dict:
  """Every setting that changes what is trained, dotted names -> JSON values."""
  return {k: v for k, v in _flat(dataclasses.asdict(cfg)).items() if k not in NOT_TRAINING}


def normalised(key: Mapping[str, Any]) -> dict:
  """A training key recorded by an older version, as today's code would write it: settings added
  since take the values that reproduce what was trained (`train.config.from_dict`)."""
  nested: dict = {}
  for name, value in key.items():
    *parents, leaf = name.split(".")
    d = nested
    for part in parents:
      d = d.setdefault(part, {})
    d[leaf] = value
  nested.setdefault("loss", {})
  return training_key(train_config.from_dict(nested))


def overrides(key: Mapping[str, Any]) -> dict:
  """The settings of a training key that differ from its preset's defaults."""
  preset = training_key(train_config.preset(key["preset"], policy=key["model.policy"]))
  return {k: v for k, v in key.items() if preset.get(k) != v}


def _short(name: str) -> str:
  return name.removeprefix("model.")


def _value(v) -> str:
  return ",".join(map(str, v)) if isinstance(v, list) else str(v)


def row_names(keys: Sequence[Mapping[str, Any]]) -> list[str]:
  """A readable, unique name for each distinct training key (keys must be distinct)."""
  if len({key_id(k) for k in keys}) != len(keys):
    raise ValueError("row_names needs distinct training keys")
  labels = [_label(k) for k in keys]
  changed = set().union(*(overrides(k) for k in keys)) | {"preset"}
  differing = [f for f in sorted(changed, key=lambda f: (f != "preset", f))
               if f != "model.policy" and len({json.dumps(k.get(f)) for k in keys}) > 1]

  def name(key, label, fields):
    shown = [f"{_short(f)}={_value(key.get(f))}" for f in fields]
    return f"{label} ({', '.join(shown)})" if shown else label

  names = [name(k, lab, [f for f in differing if not (lab == "ACT" and f in SKILLPLUG_ONLY)])
           for k, lab in zip(keys, labels)]
  if len(set(names)) != len(names):  # ACT rows that differ only in settings ACT ignores
    names = [name(k, lab, differing) for k, lab in zip(keys, labels)]
  return names


def group_rows(results: Sequence[Mapping[str, Any]]) -> dict:
  """Results (each with 'config': its training key, and 'train_seed') -> {row name: {label,
  config, overrides, seeds}}, rows in order of first appearance, seeds likewise."""
  keys = {}
  for r in results:
    keys.setdefault(key_id(r["config"]), r["config"])
  rows = {}
  for name, (i, key) in zip(row_names(list(keys.values())), keys.items()):
    seeds = list(dict.fromkeys(r["train_seed"] for r in results if key_id(r["config"]) == i))
    rows[name] = dict(label=_label(key), config=key, overrides=overrides(key), seeds=seeds)
  return rows

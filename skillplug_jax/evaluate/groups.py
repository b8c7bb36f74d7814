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

A result carries its run's overrides (`row_fields`), read against the preset's
settings as the run recorded them when it was trained (`experiment.RunRecord`),
so editing a config file later does not rename old rows. Results from before
carry none: theirs are read against today's config file, with a warning.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from typing import Any, Mapping, Sequence

from skillplug_jax import experiment, losses
from skillplug_jax.model import config as model_config
from skillplug_jax.model.plug import PlugConfig
from skillplug_jax.train import config as train_config

# Where and how often, not what: two runs differing only in these trained the same thing.
NOT_TRAINING = frozenset({"seed", "workdir", "data_dir", "init_from", "log_every", "ckpt_every",
                          "keep_checkpoints"})
# Settings only ACT+SkillPlug reads: an ACT row's name never mentions them.
# (model.plug.site is not among them: it also decides ACT's light head.)
SKILLPLUG_ONLY = frozenset({f"model.plug.{f.name}" for f in dataclasses.fields(PlugConfig) if f.name != "site"}
                           | {"loss.kl", "loss.bsa", "loss.sd", "loss.sd_kind", "loss.sd_usage_weighted"}
                           | {f"loss.{name}" for name in losses.AUX_TERMS})


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
  since take the values that reproduce what was trained (`train.config.from_dict`). A few-shot
  result's protocol fields (`fewshot.*`, `experiments.pipeline.protocol_fields`) stay as they are."""
  protocol = {k: v for k, v in key.items() if k.startswith("fewshot.")}
  nested: dict = {}
  for name, value in key.items():
    if name in protocol:
      continue
    *parents, leaf = name.split(".")
    d = nested
    for part in parents:
      d = d.setdefault(part, {})
    d[leaf] = value
  nested.setdefault("loss", {})
  return {**training_key(train_config.from_dict(nested)), **protocol}


def normalised_result(r: Mapping[str, Any]) -> dict:
  """A result as today's code writes it: its training key `normalised`, its overrides under
  today's names (a removed arm at its neutral value is no override: `model.config.REMOVED_ARMS`)."""
  out = dict(r, config=normalised(r["config"]))
  if "overrides" in r:
    out["overrides"] = {model_config.legacy_name(k): v for k, v in r["overrides"].items()
                        if k not in model_config.REMOVED_ARMS and k != "loss.distill"}
  return out


def overrides(key: Mapping[str, Any], defaults: Mapping[str, Any]) -> dict:
  """The settings of a training key that differ from `defaults`, its preset's training key."""
  return {k: v for k, v in key.items() if defaults.get(k) != v}


def row_fields(cfg: train_config.TrainConfig, record: experiment.RunRecord) -> dict:
  """What a result carries to be tabulated: its row's label, training key and overrides
  (against the preset's settings as `record`, the run's, holds them), and its seed."""
  key = training_key(cfg)
  return dict(policy=policy_label(cfg), train_seed=cfg.seed, preset=cfg.preset, config=key,
              overrides=overrides(key, training_key(record.defaults)))


def todays_overrides(key: Mapping[str, Any]) -> dict:
  """The overrides of a training key against today's config file (results that carry none)."""
  return overrides(key, training_key(experiment.preset(key["preset"], key["model.policy"])))


# A plug setting is shown by the name its rows were published under before it moved into
# model.plug (issue 40): num_skills=2, plug_site=decoder.
_SHOWN = {f"model.plug.{new}": old for old, new in model_config.LEGACY_PLUG_FIELDS.items()}


def _published_order(name: str) -> str:
  """Where a setting stands in a row's name: by its name before issue 40 nested the plug's."""
  return f"model.{_SHOWN[name]}" if name in _SHOWN else name


def _short(name: str) -> str:
  return _SHOWN.get(name, name.removeprefix("model."))


def _value(v) -> str:
  return ",".join(map(str, v)) if isinstance(v, list) else str(v)


def row_names(keys: Sequence[Mapping[str, Any]], changes: Sequence[Mapping[str, Any]]) -> list[str]:
  """A readable, unique name for each distinct training key (keys must be distinct);
  changes[i]: key i's overrides."""
  if len({key_id(k) for k in keys}) != len(keys):
    raise ValueError("row_names needs distinct training keys")
  labels = [_label(k) for k in keys]

  def differing(fields):
    return [f for f in sorted(fields, key=lambda f: (f != "preset", _published_order(f)))
            if f != "model.policy" and len({json.dumps(k.get(f)) for k in keys}) > 1]

  def name(key, label, fields):
    parts = [f"{_short(f)}={_value(key.get(f))}" for f in fields]
    return f"{label} ({', '.join(parts)})" if parts else label

  shown = differing(set().union(*changes) | {"preset"})
  names = [name(k, lab, [f for f in shown if not (lab == "ACT" and f in SKILLPLUG_ONLY)])
           for k, lab in zip(keys, labels)]
  if len(set(names)) != len(names):  # ACT rows that differ only in settings ACT ignores
    names = [name(k, lab, shown) for k, lab in zip(keys, labels)]
  if len(set(names)) != len(names):  # runs of one preset recorded with different settings: all that differ
    shown = differing({f for k in keys for f in k})
    names = [name(k, lab, shown) for k, lab in zip(keys, labels)]
  return names


def group_rows(results: Sequence[Mapping[str, Any]]) -> dict:
  """Results (each with 'config': its training key, 'overrides' and 'train_seed') -> {row name:
  {label, config, overrides, seeds}}, rows in order of first appearance, seeds likewise."""
  keys, changes = {}, {}
  for r in results:
    i = key_id(r["config"])
    keys.setdefault(i, r["config"])
    if "overrides" in r:
      changes.setdefault(i, r["overrides"])
  old = [i for i in keys if i not in changes]
  if old:
    presets = sorted({keys[i]["preset"] for i in old})
    print(f"warning: {len(old)} row(s) of results that record no overrides are named against today's "
          f"config file(s) {', '.join(f'{p}.py' for p in presets)}", file=sys.stderr)
    changes.update({i: todays_overrides(keys[i]) for i in old})
  rows = {}
  for name, (i, key) in zip(row_names(list(keys.values()), [changes[i] for i in keys]), keys.items()):
    seeds = list(dict.fromkeys(r["train_seed"] for r in results if key_id(r["config"]) == i))
    rows[name] = dict(label=_label(key), config=key, overrides=changes[i], seeds=seeds)
  return rows

"""Experiment configs: one small file per preset, table or figure (big_vision's pattern).

Each module here defines `get_config() -> Experiment`: the training
settings (`train`, a `TrainConfig` whose `preset` is the module's name) and
the evaluation protocol around them. Its docstring names the command that
runs it. A config is loaded by name and overridden from the command line
with dotted `key=value` settings:

    exp = configs.get("paper_cpu", ["seeds=0", "train.max_steps=200", "fewshot.steps=50"])
    cfg = exp.train_config("skillplug", seed=0)

`skillplug pretrain --config NAME --set KEY=VALUE` overrides `train`'s
fields (`--set model.hidden=128`); the pipeline (`python -m
experiments.pipeline --config NAME --set KEY=VALUE`) overrides the whole
experiment (`--set train.model.hidden=128 --set seeds=0,1`).
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from pathlib import Path
from typing import Iterable

from skillplug_jax.train import config as train_config
from skillplug_jax.train.config import TrainConfig


@dataclasses.dataclass(frozen=True)
class FewShot:
  """The few-shot protocol: fine-tune each multi-task run on each unseen task, then evaluate it.

  The paper's groups: ACT+SkillPlug retrains the router and the action
  head (encoder, skill library, interactor and posterior frozen); ACT
  retrains the action head only.
  """
  taskset: str = "discoverse_fewshot4"
  demos: int = 10  # demonstrations per unseen task
  steps: int = 500  # fine-tuning steps per task; 0: the source run's own `epochs`
  trainable_act: tuple[str, ...] = ("action_head",)
  trainable_skillplug: tuple[str, ...] = ("action_head", "router")

  def trainable(self, policy: str) -> tuple[str, ...]:
    return tuple(sorted(self.trainable_skillplug if policy == "skillplug" else self.trainable_act))


@dataclasses.dataclass(frozen=True)
class Variant:
  """One arm of an experiment that varies a config (an ablation, a sweep): its runs go to
  OUT/<name>/, its table row is named `label`, and `overrides` (the pipeline's --set syntax,
  `train.loss.sd=0`, `seeds=0`, `run_fewshot=false`) make it from the config."""
  name: str
  overrides: tuple[str, ...] = ()
  label: str = ""  # default: the name


@dataclasses.dataclass(frozen=True)
class Experiment:
  """Training settings plus the protocol that evaluates them (`experiments.pipeline`)."""
  train: TrainConfig  # model.policy and seed are set per run by `train_config`
  policies: tuple[str, ...] = ("act", "skillplug")
  seeds: tuple[int, ...] = (0,)  # training seeds: the replicates of each table row
  trials: int = 50  # paired closed-loop trials per task (trial i: the same start for every run)
  eval_seed: int = 1000
  eval_batch: int = 50  # environments simulated at once
  fewshot: FewShot = FewShot()
  run_fewshot: bool = True
  workers: int = 2  # jobs (one (policy, seed) each) run side by side in this many processes; 1: in-process
  # Several arms (ablations, sweeps): each is this experiment with its overrides. Empty: one arm,
  # the experiment itself, whose runs go to OUT/ as they always did.
  variants: tuple[Variant, ...] = ()
  # A published pipeline summary (summary.json) whose results join the tables as rows that are
  # read, not run: the baseline a sweep is read against (e.g. docs/results/paper_cpu/summary.json).
  reference: str = ""
  command: str = ""  # the command that runs this config (filled from the docstring's first line)

  def train_config(self, policy: str, seed: int) -> TrainConfig:
    return dataclasses.replace(self.train, model=dataclasses.replace(self.train.model, policy=policy), seed=seed)


def expand(exp: Experiment) -> list[tuple[Variant, Experiment]]:
  """The arms of `exp`: (variant, the experiment it runs), or one unnamed arm when it has none."""
  if not exp.variants:
    return [(Variant(""), exp)]
  names_seen = [v.name for v in exp.variants]
  bad = [n for n in names_seen if not n or "/" in n or n.startswith(".")]
  if bad or len(set(names_seen)) != len(names_seen):
    raise ValueError(f"variant names must be distinct folder names, got {names_seen}")
  base = dataclasses.replace(exp, variants=())
  return [(v, train_config.override(base, v.overrides)) for v in exp.variants]


def only(exp: Experiment, wanted: str, config: str = "") -> Experiment:
  """`exp` with only the variants named in `wanted` (comma-separated; empty: all of them)."""
  if not wanted:
    return exp
  names_wanted = wanted.split(",")
  unknown = sorted(set(names_wanted) - {v.name for v in exp.variants})
  if unknown:
    raise ValueError(f"unknown variant(s) {unknown} of config {config or exp.train.preset!r}; it has: "
                     f"{', '.join(v.name for v in exp.variants) or 'none'}")
  return dataclasses.replace(exp, variants=tuple(v for v in exp.variants if v.name in names_wanted))


def names() -> list[str]:
  return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if not m.name.startswith("_"))


def get(name: str, overrides: Iterable[str] = ()) -> Experiment:
  """The experiment config `name` (a module of this package), with `key=value` overrides applied."""
  if name not in names():
    raise ValueError(f"unknown config {name!r}; configs in experiments/configs/: {', '.join(names())}")
  module = importlib.import_module(f"{__name__}.{name}")
  exp = module.get_config()
  if exp.train.preset not in names():
    raise ValueError(f"experiments/configs/{name}.py: train.preset {exp.train.preset!r} names no config; it "
                     "must name the config its training settings come from (runs record it)")
  if not exp.command and module.__doc__:
    exp = dataclasses.replace(exp, command=module.__doc__.strip().splitlines()[0].strip())
  return train_config.override(exp, overrides)

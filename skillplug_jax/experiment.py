"""Experiment configs: one small file per preset, table or figure (big_vision's pattern), and what a run
records of the config it was trained from.

A config file (experiments/configs/NAME.py) defines `get_config() -> Experiment`:
the training settings (`train`, a `TrainConfig` whose `preset` is the file's name)
and the evaluation protocol around them. Its docstring names the command that runs
it. Config files are pure data: they import this module and the config classes,
and are loaded by file, so this library never imports the `experiments` package.
A config is loaded by name (or by path) and overridden with dotted `key=value`
settings:

    exp = experiment.get("cpu", ["seeds=0", "train.max_steps=200", "fewshot.steps=50"])
    cfg = exp.train_config("skillplug", seed=0)

A run records, in its config.json (`train.run_files`), a `RunRecord`
(`train.run_record`): the config's name, its few-shot protocol and its training
settings for the run's policy. Its table row is named, and it is adapted, from
that record (`read_record`), so an old run keeps its meaning when the config
file is edited.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path
from typing import Iterable

from skillplug_jax import validation
from skillplug_jax.model.config import POLICIES
from skillplug_jax.train import config as train_config
from skillplug_jax.train import run_files
from skillplug_jax.train.config import TrainConfig
# The few-shot protocol and the run record live beside the training loop that writes them;
# config files import them from here (`from skillplug_jax.experiment import Experiment, FewShot`).
from skillplug_jax.train.run_record import (FewShot, RunRecord, Trainable, record_from_dict,  # noqa: F401
                                            record_to_dict)


# Each (policy, seed) is one run directory: a policy or seed given twice would train it twice at once.
_EXPERIMENT_RULES = dict(
    policies=validation.each(validation.one_of(POLICIES), nonempty=True, distinct=True),
    seeds=validation.each(validation.count(0), nonempty=True, distinct=True), trials=validation.count(1),
    eval_seed=validation.count(0), eval_batch=validation.count(1), run_fewshot=validation.flag(),
    workers=validation.count(1))


def _variant_names_ok(exp: "Experiment") -> bool:
  names_seen = [v.name for v in exp.variants]
  return (len(set(names_seen)) == len(names_seen)
          and all(n and "/" not in n and not n.startswith(".") for n in names_seen))


def _adapted_sources_ok(exp: "Experiment") -> bool:
  trains = {v.name for v in exp.variants if not v.adapts}
  return all(v.adapts in trains for v in exp.variants if v.adapts)


_EXPERIMENT_RELATIONS = (
    validation.Relation("variants", _variant_names_ok,
                        lambda e: "distinct folder names (non-empty, no '/', not starting with '.')",
                        lambda e: [v.name for v in e.variants]),
    validation.Relation("variants", _adapted_sources_ok,
                        lambda e: "an `adapts` that names a variant of the same experiment which trains its "
                                  "own runs (adapts nothing itself)",
                        lambda e: [v.name for v in e.variants]),
)


@dataclasses.dataclass(frozen=True)
class Variant:
  """One arm of an experiment that varies a config (an ablation, a sweep): its runs go to
  OUT/<name>/, its table row is named `label`, and `overrides` (the pipeline's --set syntax,
  `train.loss.sd=0`, `seeds=0`, `run_fewshot=false`) make it from the config."""
  name: str
  overrides: tuple[str, ...] = ()
  label: str = ""  # default: the name
  # Another variant's name: this arm trains nothing of its own; it adapts that arm's pretrained runs
  # by its own few-shot protocol (its overrides may change `fewshot.*` and the policies and seeds it
  # adapts, not training), its fine-tunes beside the source's, in RUN_fewshot_<name>/.
  adapts: str = ""


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

  def __post_init__(self):
    validation.check(self, "", _EXPERIMENT_RULES, _EXPERIMENT_RELATIONS)

  def train_config(self, policy: str, seed: int) -> TrainConfig:
    return dataclasses.replace(self.train, model=dataclasses.replace(self.train.model, policy=policy), seed=seed)


def expand(exp: Experiment) -> list[tuple[Variant, Experiment]]:
  """The arms of `exp`: (variant, the experiment it runs), or one unnamed arm when it has none."""
  if not exp.variants:
    return [(Variant(""), exp)]
  base = dataclasses.replace(exp, variants=())
  arms = []
  for v in exp.variants:
    try:
      arms.append((v, train_config.override(base, v.overrides)))
    except validation.ConfigError:  # a bad value: named by its key (what the pipeline's workers pickle)
      raise
    except ValueError as e:  # an unknown setting: which arm, as well as which key
      raise ValueError(f"variant {v.name!r}: {e}") from e
  by_name = dict((v.name, e) for v, e in arms)
  for v, e in arms:
    if v.adapts:
      _check_adapts(v, e, by_name[v.adapts])
  return arms


def _check_adapts(v: Variant, arm: Experiment, source: Experiment) -> None:
  """An adapting arm must find its source's runs: the same training, policies and seeds among its."""
  if arm.train != source.train:
    diffs = run_files.config_differences(source.train, arm.train, "train.")
    raise ValueError(f"variant {v.name!r} adapts {v.adapts!r} but trains otherwise ({'; '.join(diffs)}): an arm "
                     "that adapts another may change only the few-shot protocol (fewshot.*)")
  for what in ("policies", "seeds"):
    missing = sorted(set(getattr(arm, what)) - set(getattr(source, what)), key=str)
    if missing:
      raise ValueError(f"variant {v.name!r} adapts {v.adapts!r}, whose runs have no {what} {missing}")


def only(exp: Experiment, wanted: str, config: str = "") -> Experiment:
  """`exp` with only the variants named in `wanted` (comma-separated; empty: all of them)."""
  if not wanted:
    return exp
  names_wanted = wanted.split(",")
  unknown = sorted(set(names_wanted) - {v.name for v in exp.variants})
  if unknown:
    raise ValueError(f"unknown variant(s) {unknown} of config {config or exp.train.preset!r}; it has: "
                     f"{', '.join(v.name for v in exp.variants) or 'none'}")
  # an arm that adapts another's runs needs that arm (its runs are read back, or trained first)
  names_wanted += [v.adapts for v in exp.variants if v.name in names_wanted and v.adapts]
  return dataclasses.replace(exp, variants=tuple(v for v in exp.variants if v.name in names_wanted))


def configs_dir() -> Path:
  """The repository's experiments/configs/: beside this package in a checkout, else under the cwd."""
  beside = Path(__file__).resolve().parents[1] / "experiments" / "configs"
  return beside if beside.is_dir() else Path.cwd() / "experiments" / "configs"


def directory(name: str, configs: str | Path | None = None) -> Path:
  """The directory config `name` is read from: a path's own (NAME.py), else `configs`, by default
  `configs_dir()`. Its train.preset is read from there too (`record`)."""
  if name.endswith(".py"):
    return Path(name).parent
  return Path(configs) if configs is not None else configs_dir()


def _locate(name: str, configs: str | Path | None) -> tuple[str, Path]:
  """(config name, its directory)."""
  return (Path(name).stem if name.endswith(".py") else name), directory(name, configs)


def _shown(where: Path) -> str:
  try:
    return f"{where.resolve().relative_to(Path.cwd().resolve())}/"
  except ValueError:
    return f"{where}/"


def names(configs: str | Path | None = None) -> list[str]:
  """The configs in `configs` (default: the repository's experiments/configs/)."""
  where = Path(configs) if configs is not None else configs_dir()
  return sorted(p.stem for p in where.glob("*.py") if not p.name.startswith("_"))


def _module(name: str, configs: str | Path | None):
  name, where = _locate(name, configs)
  if name not in names(where):
    raise ValueError(f"unknown config {name!r}; configs in {_shown(where)}: {', '.join(names(where))}")
  spec = importlib.util.spec_from_file_location(f"skillplug_config_{name}", where / f"{name}.py")
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def load(name: str, configs: str | Path | None = None) -> Experiment:
  """The experiment config file `name` defines, as written (no command filled in, no overrides):
  what a config built on another reads, `load("cpu", Path(__file__).parent)`."""
  return _module(name, configs).get_config()


def get(name: str, overrides: Iterable[str] = (), configs: str | Path | None = None) -> Experiment:
  """The experiment config `name` (a file of `configs`, or a path to one), with `key=value` overrides."""
  module = _module(name, configs)
  name, where = _locate(name, configs)
  exp = module.get_config()
  if exp.train.preset not in names(where):
    raise ValueError(f"{_shown(where)}{name}.py: train.preset {exp.train.preset!r} names no config; it "
                     "must name the config its training settings come from (runs record it)")
  if not exp.command and module.__doc__:
    exp = dataclasses.replace(exp, command=module.__doc__.strip().splitlines()[0].strip())
  return train_config.override(exp, overrides)


def preset(name: str, policy: str = "skillplug", configs: str | Path | None = None) -> TrainConfig:
  """The training settings of the experiment config `name` for `policy` (seed 0)."""
  return get(name, configs=configs).train_config(policy, seed=0)


def record(exp: Experiment, policy: str, configs: str | Path | None = None) -> RunRecord:
  """What a run of `policy` under `exp` records: `exp`'s few-shot protocol, and the training
  settings of its preset (read now, from `configs`, the directory `exp` was loaded from) that
  its overrides are read against."""
  return RunRecord(exp.train.preset, exp.fewshot, preset(exp.train.preset, policy, configs))


def todays_record(preset_name: str, policy: str, run: str | Path) -> RunRecord:
  """The record of a run trained before runs kept one: built from today's config file, with a warning."""
  try:
    exp = get(preset_name)
  except ValueError as e:
    raise ValueError(f"{run} records no experiment config and its config {preset_name!r} is not in "
                     f"{_shown(configs_dir())}, so its row and few-shot protocol are unknown: {e}") from e
  print(f"warning: {run} records no experiment config; its row and few-shot protocol are read from today's "
        f"{_shown(configs_dir())}{preset_name}.py", file=sys.stderr)
  return RunRecord(preset_name, exp.fewshot, exp.train_config(policy, seed=0))


def read_record(run_dir: str | Path) -> RunRecord:
  """The run's record (`run_files.stored_record`); for a run without one, today's config file's,
  with a warning (`todays_record`)."""
  from skillplug_jax.train import run_files  # here: it loads orbax, which a config file need not
  record = run_files.stored_record(run_dir)
  if record is not None:
    return record
  cfg = run_files.read_config(run_dir)
  return todays_record(cfg.preset, cfg.model.policy, run_dir)

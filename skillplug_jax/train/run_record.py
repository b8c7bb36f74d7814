"""What a run keeps of the experiment config it was trained from (`RunRecord`), and the few-shot
protocol in it (`FewShot`, whose parameter groups are `Trainable`).

A run's config.json holds the record beside its TrainConfig (`train.run_files`), so that its
table row is named, and it is adapted, as it was trained, whatever the config file says later.
This module sits below `skillplug_jax.experiment` (which re-exports these names for config
files) so that the training loop and run files read and write records without importing it.
"""

from __future__ import annotations

import dataclasses

from skillplug_jax import validation
from skillplug_jax.model.config import POLICIES
from skillplug_jax.model.freeze import GROUPS
from skillplug_jax.train import config as train_config
from skillplug_jax.train.config import TrainConfig

_GROUPS = validation.each(validation.one_of(GROUPS), distinct=True)
_TRAINABLE_RULES = dict(act=_GROUPS, skillplug=_GROUPS)


@dataclasses.dataclass(frozen=True)
class Trainable:
  """The parameter groups (`model.freeze.GROUPS`) a few-shot fine-tune trains, per policy:
  `TrainConfig.trainable` of each fine-tune is `of(policy)`. Set as `fewshot.trainable.act=...`,
  `fewshot.trainable.skillplug=action_head,router`."""
  act: tuple[str, ...] = ("action_head",)
  skillplug: tuple[str, ...] = ("action_head", "router")

  def __post_init__(self):
    validation.check(self, "fewshot.trainable.", _TRAINABLE_RULES)

  def of(self, policy: str) -> tuple[str, ...]:
    """The groups a fine-tune of a `policy` run trains, sorted."""
    if policy not in POLICIES:
      raise ValueError(f"unknown policy {policy!r}; valid policies: {', '.join(POLICIES)}")
    return tuple(sorted(getattr(self, policy)))


# What one fine-tune adapts to: each task of `FewShot.taskset` (DISCOVERSE's protocol), or each of its
# comma-separated parts, a whole suite (the paper's LIBERO protocol: adapt to a suite, 5 demos per task).
FEWSHOT_UNITS = ("task", "taskset")

_FEWSHOT_RULES = dict(taskset=validation.text(), demos=validation.count(1),
                      steps=validation.count(0, " (0: the source run's own `epochs`)"),
                      trainable=validation.Rule(lambda v: isinstance(v, Trainable),
                                                "a Trainable (groups per policy: Trainable(act=..., skillplug=...))"),
                      marginal_terms=validation.flag(), train_overrides=validation.each(validation.text()),
                      per=validation.one_of(FEWSHOT_UNITS))


@dataclasses.dataclass(frozen=True)
class FewShot:
  """The few-shot protocol: fine-tune each multi-task run on each unseen task, then evaluate it.

  The paper's groups (`trainable`): ACT+SkillPlug retrains the router and the
  action head (encoder, skill library, interactor and posterior frozen); ACT
  retrains the action head only.
  """
  taskset: str = "discoverse_fewshot4"
  demos: int = 10  # demonstrations per unseen task
  steps: int = 500  # fine-tuning steps per task; 0: the source run's own `epochs`
  trainable: Trainable = Trainable()
  # Ours (issue 27): whether the fine-tune keeps the source's term on the batch's mean routing
  # (loss.usage). It asks a batch to spread over the skills, which suits pretraining's batch of
  # many tasks; a few-shot batch holds one task. False: it weighs 0.
  marginal_terms: bool = True
  # TrainConfig overrides (train/config.py syntax, `loss.router_label=0`) of the fine-tune alone,
  # applied after the rest of this protocol (`fewshot.fewshot_config`); pretraining keeps its own.
  train_overrides: tuple[str, ...] = ()
  # "task": one fine-tune per task of `taskset`, evaluated on it; "taskset": one per comma-separated
  # part of `taskset` (a LIBERO suite), on every task of the part, evaluated on each of them.
  per: str = "task"

  def __post_init__(self):
    validation.check(self, "fewshot.", _FEWSHOT_RULES)


@dataclasses.dataclass(frozen=True)
class RunRecord:
  """What a run keeps of its experiment config: enough to name its table row and to adapt it."""
  config: str  # the config file's name (its train.preset)
  fewshot: FewShot  # the few-shot protocol the run is adapted with by default
  defaults: TrainConfig  # the config's training settings for the run's policy: its row names what differs


def record_to_dict(rec: RunRecord) -> dict:
  return dataclasses.asdict(rec)


# A record written before the groups were one `Trainable` kept them as two fields of FewShot.
_LEGACY_TRAINABLE = {"trainable_act": "act", "trainable_skillplug": "skillplug"}


def _tuples(d: dict) -> dict:
  return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


def fewshot_from_dict(d: dict) -> FewShot:
  d = dict(d)
  groups = dict(d.pop("trainable", None) or {})
  for old, new in _LEGACY_TRAINABLE.items():
    if old in d:
      groups[new] = d.pop(old)
  return FewShot(trainable=Trainable(**_tuples(groups)), **_tuples(d))


def record_from_dict(d: dict) -> RunRecord:
  return RunRecord(d["config"], fewshot_from_dict(d["fewshot"]), train_config.from_dict(d["defaults"]))

"""Training configuration: a frozen dataclass and command-line overrides.

The presets are experiment configs (experiments/configs/NAME.py);
`skillplug_jax.experiment.preset` reads one's training settings:

    cfg = experiment.preset("quick", policy="act")
    cfg = override(cfg, ["lr=3e-4", "model.hidden=128", "loss.sd=0.5"])
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

from envs.names import BACKENDS  # cheap: not the suite (envs/__init__.py)
from skillplug_jax import validation
from skillplug_jax.data.segments import LABELLERS as SKILL_LABELLERS  # numpy only
from skillplug_jax.losses import LossWeights
from skillplug_jax.model import config as model_config
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.freeze import GROUPS


LR_SCHEDULES = ("constant", "cosine")


_count = validation.count
_RULES = dict(
    preset=validation.text(), taskset=validation.text(), demos=_count(1), data_seed=_count(0),
    data_dir=validation.text(), backend=validation.one_of(BACKENDS),
    skill_labels=validation.one_of(("",) + SKILL_LABELLERS), batch_size=_count(1),
    lr=validation.number(above=0), weight_decay=validation.number(0),
    grad_clip=validation.number(note=" (<= 0: no clipping)"), warmup_steps=_count(0),
    lr_schedule=validation.one_of(LR_SCHEDULES), epochs=validation.number(above=0),
    max_steps=_count(0, " (0: train `epochs`)"), seed=_count(0),
    trainable=validation.each(validation.one_of(GROUPS), distinct=True, note=" (empty: all)"),
    log_every=_count(1), ckpt_every=_count(1), keep_checkpoints=_count(1))


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  preset: str  # the experiment config these settings come from (rows are named against it)
  model: ModelConfig
  loss: LossWeights = LossWeights()
  # data: the dataset `skillplug demos` writes for these fields
  taskset: str = "discoverse7"  # the tasks trained on
  data_taskset: str = ""  # the dataset they are read from (default: taskset); few-shot reads one task of many
  demos: int = 300  # per task; images follow model.use_images and model.image_size
  data_seed: int = 0
  data_dir: str = "results/datasets"
  backend: str = "auto"  # physics of the demonstrations (envs.BACKENDS); resolved by `loop.train`, the run records it
  # Ours (issue 27): every step's `skill_label` mined from the demonstrations by this labeller
  # (data/segments.py), which loss.router_label trains the router to predict. '': none (the toy:
  # its ground-truth primitive, the oracle).
  skill_labels: str = ""
  # optimisation (ACT: AdamW, lr 1e-5 backbone / 1e-4 rest, weight decay 1e-4)
  batch_size: int = 16
  lr: float = 1e-4
  weight_decay: float = 1e-4
  grad_clip: float = 1.0  # global-norm clipping (ACT: none); <= 0 turns it off
  warmup_steps: int = 0
  # after warm-up: 'constant' (ACT), or 'cosine' (decays to 0 at the last step, for short budgets)
  lr_schedule: str = "constant"
  epochs: float = 6000.0  # ACT epochs: one random timestep per episode each
  max_steps: int = 0  # > 0: train this many steps instead of `epochs`
  seed: int = 0
  # which parameter groups train (empty: all); few-shot sets router/action_head
  trainable: tuple[str, ...] = ()
  init_from: str = ""  # checkpoint directory whose parameters start this run
  # bookkeeping
  workdir: str = ""  # default: results/runs/<taskset>_<policy>_<preset>_seed<seed>
  log_every: int = 50
  ckpt_every: int = 1000
  keep_checkpoints: int = 2

  def __post_init__(self):
    validation.check(self, "", _RULES)

  @property
  def run_dir(self) -> Path:
    if self.workdir:
      return Path(self.workdir)
    return Path("results/runs") / f"{self.taskset}_{self.model.policy}_{self.preset}_seed{self.seed}"

  def num_steps(self, num_episodes: int) -> int:
    if self.max_steps > 0:
      return self.max_steps
    return max(1, int(round(self.epochs * num_episodes / self.batch_size)))


def _parse(value: str, typ):
  origin = typing.get_origin(typ)
  if typ is bool:
    if value.lower() in ("1", "true", "yes"):
      return True
    if value.lower() in ("0", "false", "no"):
      return False
    raise ValueError(f"not a boolean: {value!r}")
  if origin is tuple:
    args = typing.get_args(typ)
    items = [v for v in value.split(",") if v]
    return tuple(_parse(v, args[0]) for v in items)
  if typ in (int, float, str):
    return typ(value)
  raise ValueError(f"cannot set a field of type {typ}")


def override(cfg, assignments: typing.Iterable[str]):
  """Apply `key=value` (dotted for nested dataclasses: model.hidden=128).

  The result is checked once all are applied (fields that constrain each other, such as
  model.hidden and model.heads, may be set in any order); a bad value is named by its key.
  """
  with validation.deferred():
    for item in assignments:
      if "=" not in item:
        raise ValueError(f"override {item!r} is not key=value")
      key, value = item.split("=", 1)
      cfg = _set(cfg, key.strip().split("."), value.strip(), key)
  validation.check_all(cfg)
  return cfg


def _set(obj, path, value, full_key):
  hints = typing.get_type_hints(type(obj))
  name = path[0]
  if name not in hints:
    valid = ", ".join(f.name for f in dataclasses.fields(obj))
    raise ValueError(f"unknown setting {full_key!r}; {type(obj).__name__} has: {valid}")
  if len(path) > 1:
    return dataclasses.replace(obj, **{name: _set(getattr(obj, name), path[1:], value, full_key)})
  if dataclasses.is_dataclass(getattr(obj, name)):  # a group of settings: one of them is set
    inner = ", ".join(f.name for f in dataclasses.fields(getattr(obj, name)))
    first = dataclasses.fields(getattr(obj, name))[0].name
    raise ValueError(f"{full_key} holds settings ({inner}): set one of them, e.g. {full_key}.{first}=...")
  try:
    parsed = _parse(value, hints[name])
  except ValueError as e:
    raise ValueError(f"{full_key}={value!r}: {e}") from e
  return dataclasses.replace(obj, **{name: parsed})


def to_dict(cfg) -> dict:
  return dataclasses.asdict(cfg)


def from_dict(d: dict) -> TrainConfig:
  """A TrainConfig as a run's config.json holds it, from this version or an older one
  (`model.config.from_dict`; the loss terms removed in issue 40 must hold their neutral values)."""
  d = dict(d)
  model = model_config.from_dict(d.pop("model"))
  loss = dict(d.pop("loss"))
  loss.pop("distill", None)  # it weighed only with model.fusion_source='posterior', which check_removed names
  model_config.check_removed({f"loss.{k}": loss.pop(k) for k in ("load_balance", "router_z")
                              if k in loss})
  d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
  return TrainConfig(model=model, loss=LossWeights(**loss), **d)

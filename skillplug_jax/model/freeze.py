"""Freezing by parameter group, for few-shot adaptation.

Octo's pattern: a trainable set of names becomes a pytree of labels for
`optax.multi_transform`; frozen leaves get `optax.set_to_zero()`, so they
receive no update and no weight decay, and the training loop stays the same.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping

import jax
import optax

GROUPS = ("encoder", "cvae", "skills", "interactor", "router", "posterior", "action_head",
          "action_proj", "adapter")  # action_proj: only with PlugConfig.site="decoder"; adapter: adapter_width > 0


def _groups_tree(params: Mapping[str, Any]) -> Mapping[str, Any]:
  """Accept either `variables` ({'params': ...}) or the params tree itself."""
  if set(params.keys()) == {"params"}:
    return params["params"]
  return params


def param_groups(params: Mapping[str, Any]) -> set[str]:
  """The top-level group names present in a parameter tree."""
  return set(_groups_tree(params).keys())


def _check(params, trainable: Iterable[str]) -> frozenset[str]:
  trainable = frozenset(trainable)
  unknown = trainable - param_groups(params)
  if unknown:  # a typo would otherwise silently freeze everything
    raise ValueError(f"unknown parameter groups {sorted(unknown)}; "
                     f"this tree has {sorted(param_groups(params))}")
  return trainable


def _label_tree(params, fn):
  """Map each top-level group's leaves to fn(group name), keeping the structure."""
  def map_groups(groups):
    return {name: jax.tree.map(lambda _: fn(name), sub) for name, sub in groups.items()}
  if set(params.keys()) == {"params"}:
    return {"params": map_groups(params["params"])}
  return map_groups(params)


def trainable_mask(params: Mapping[str, Any], trainable: Iterable[str]):
  """Pytree of bools shaped like `params`: True where the leaf's group trains."""
  trainable = _check(params, trainable)
  return _label_tree(params, lambda name: name in trainable)


def freeze_labels(params: Mapping[str, Any], trainable: Iterable[str]):
  """Pytree of 'trainable' / 'frozen' labels for `optax.multi_transform`."""
  trainable = _check(params, trainable)
  return _label_tree(params, lambda name: "trainable" if name in trainable else "frozen")


def masked_optimizer(optimizer: optax.GradientTransformation, params: Mapping[str, Any],
                     trainable: Iterable[str]) -> optax.GradientTransformation:
  """`optimizer` on the trainable groups, zero updates everywhere else."""
  return optax.multi_transform(
      {"trainable": optimizer, "frozen": optax.set_to_zero()},
      freeze_labels(params, trainable))

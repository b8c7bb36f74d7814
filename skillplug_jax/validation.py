"""Settings checked when a config is built, so that a bad value stops the command before any work.

Each config dataclass keeps a table {field: Rule} (and, where fields constrain each other, a
few relations) and calls `check` from its __post_init__. The error names the field, its value
and what is allowed:

    model.plug.num_skills must be an integer >= 1, got 0

A field is named from the config that holds it (`model.`, `loss.`, `fewshot.`); `override`
names it by the full key it was set with (`train.model.plug.num_skills` for the pipeline's --set).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from typing import Any, Callable, Iterable, Mapping, NamedTuple


class ConfigError(ValueError):
  """A setting outside what its field allows."""

  def __init__(self, field: str, value: Any, allowed: str, section: str = ""):
    self.field, self.value, self.allowed, self.section = field, value, allowed, section
    super().__init__(f"{section}{field} must be {allowed}, got {value!r}")

  def __reduce__(self):  # pickles (from a pipeline worker) with its own arguments, not the message
    return type(self), (self.field, self.value, self.allowed, self.section)

  def within(self, path: str) -> "ConfigError":
    """The same error named from the config that holds this one's at `path` ('train.model')."""
    return ConfigError(f"{path}.{self.field}", self.value, self.allowed)


class Rule(NamedTuple):
  test: Callable[[Any], bool]
  allowed: str  # completes "<field> must be ..."


class Relation(NamedTuple):
  """A rule on several fields, reported on one of them."""
  field: str
  test: Callable[[Any], bool]
  allowed: Callable[[Any], str]
  value: Callable[[Any], Any] | None = None  # what the error shows (default: the field's value)


def _is_int(v) -> bool:
  return isinstance(v, int) and not isinstance(v, bool)


def _is_real(v) -> bool:
  return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def count(low: int = 1, note: str = "") -> Rule:
  """An integer >= low (counts, steps, seeds)."""
  return Rule(lambda v: _is_int(v) and v >= low, f"an integer >= {low}{note}")


def number(low: float | None = None, high: float | None = None, above: float | None = None,
           note: str = "") -> Rule:
  """A finite real number, optionally in [low, high] or > above."""
  def test(v):
    return (_is_real(v) and (low is None or v >= low) and (high is None or v <= high)
            and (above is None or v > above))
  if low is not None and high is not None:
    text = f"in [{low:g}, {high:g}]"
  elif above is not None:
    text = f"> {above:g}"
  elif low is not None:
    text = f">= {low:g}"
  else:
    text = "a finite number"
  return Rule(test, text + note)


def one_of(values: Iterable[str]) -> Rule:
  values = tuple(values)
  return Rule(lambda v: isinstance(v, str) and v in values, f"one of {values}")


def text() -> Rule:
  return Rule(lambda v: isinstance(v, str) and bool(v), "a non-empty string")


def flag() -> Rule:
  return Rule(lambda v: isinstance(v, bool), "true or false")


def each(rule: Rule, nonempty: bool = False, distinct: bool = False, length: int | None = None,
         note: str = "") -> Rule:
  """A tuple whose items all pass `rule`."""
  def test(v):
    return (isinstance(v, tuple) and all(rule.test(x) for x in v) and (bool(v) or not nonempty)
            and (len(set(v)) == len(v) or not distinct) and (length is None or len(v) == length))
  if length is not None:
    shape = f"a tuple of {length} "
  else:
    shape = "a non-empty tuple of " if nonempty else "a tuple of "
  return Rule(test, f"{shape}{'distinct ' if distinct else ''}{_plural(rule.allowed)}{note}")


def _plural(allowed: str) -> str:
  """'an integer >= 0' -> 'integers >= 0'; 'one of (...)' -> 'values from (...)'."""
  if allowed.startswith("one of "):
    return "values from " + allowed[len("one of "):]
  for article in ("an ", "a "):
    if allowed.startswith(article):
      noun, _, rest = allowed[len(article):].partition(" ")
      return f"{noun}s {rest}".strip()
  return allowed


_deferred = contextvars.ContextVar("skillplug_config_checks_deferred", default=False)


@contextlib.contextmanager
def deferred():
  """Build configs unchecked, to apply several overrides at once: a relation (hidden divisible
  by heads) must hold for the result, not after each assignment. `check_all` checks the result."""
  token = _deferred.set(True)
  try:
    yield
  finally:
    _deferred.reset(token)


def check(config, section: str, rules: Mapping[str, Rule], relations: Iterable[Relation] = ()) -> None:
  """Raise ConfigError for the first field of `config` its rules or relations reject."""
  if _deferred.get():
    return
  for name, rule in rules.items():
    value = getattr(config, name)
    if not rule.test(value):
      raise ConfigError(name, value, rule.allowed, section)
  for r in relations:
    if not r.test(config):
      value = r.value(config) if r.value else getattr(config, r.field)
      raise ConfigError(r.field, value, r.allowed(config), section)


def check_all(config, path: str = "") -> None:
  """Check `config` and every config it holds (innermost first), naming a field by its dotted
  path from `config`."""
  for f in dataclasses.fields(config):
    value = getattr(config, f.name)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
      check_all(value, f"{path}.{f.name}" if path else f.name)
  post_init = getattr(config, "__post_init__", None)
  if post_init is None:
    return
  try:
    post_init()
  except ConfigError as e:
    raise (e.within(path) if path else e) from None

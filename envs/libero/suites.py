"""LIBERO's task suites as our tasksets: the ordered tasks, their BDDL files and instructions, the
benchmark's fixed initial states and the time limits its evaluations use.

Everything but the time limits is read from the installed `libero.libero.benchmark` (task order
0, LIBERO's default), never copied into the project. The time limits are not in the package:
they are the `max_steps` of the evaluation scripts the field reports with (OpenVLA's
run_libero_eval.py, copied by openpi and LeRobot), in control steps at 20 Hz, each longer than
that suite's longest human demonstration; those scripts first send `SETTLE_STEPS` no-op actions
(objects drop onto the table) that the limit does not count.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from envs.libero.installed import quiet_benchmark

# The four suites the paper and the field report, and LIBERO-90 (LIBERO-100 less LIBERO-10).
SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")
TIME_LIMITS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520,
               "libero_90": 400}
SETTLE_STEPS = 10
INIT_STATES_PER_TASK = 50  # the benchmark's fixed initial states: trial i of a task starts from state i


class Task(NamedTuple):
  suite: str
  index: int  # position in the suite (LIBERO's task order 0)
  name: str  # LIBERO's task name, the BDDL file's stem
  language: str  # the instruction a policy is given
  bddl_file: str  # absolute path inside the installed package
  time_limit: int  # control steps


def _check_suite(suite: str) -> str:
  if suite not in SUITES:
    raise ValueError(f"unknown LIBERO suite {suite!r}; valid suites: {', '.join(SUITES)}")
  return suite


def tasks(suite: str) -> tuple[Task, ...]:
  """The suite's tasks in LIBERO's order."""
  bench = quiet_benchmark(_check_suite(suite))
  return tuple(Task(suite, i, t.name, t.language, bench.get_task_bddl_file_path(i), TIME_LIMITS[suite])
               for i, t in enumerate(bench.tasks))


def task(suite: str, which: int | str) -> Task:
  """One task of `suite`, by its index or its LIBERO name."""
  listed = tasks(suite)
  for t in listed:
    if which in (t.index, t.name):
      return t
  raise ValueError(f"unknown task {which!r} of LIBERO suite {suite!r}: it has tasks 0-{len(listed) - 1} "
                   f"({', '.join(t.name for t in listed[:3])}, ...)")


def init_states(suite: str, which: int | str) -> np.ndarray:
  """The benchmark's fixed initial states of a task, [50, 1 + nq + nv]: MuJoCo's flattened state
  as robosuite writes it (time, qpos, qvel), for `scene.set_init_state`."""
  t = task(suite, which)
  return np.asarray(quiet_benchmark(suite).get_task_init_states(t.index), dtype=np.float64)


# ---- our task names: "<suite>:<index>", and a suite's name for all its tasks (tasksets)

def is_libero(name: str) -> bool:
  """Whether a task or taskset name is LIBERO's ("libero_object", "libero_object:3")."""
  return name.split(":", 1)[0] in SUITES


def taskset(name: str) -> tuple[str, ...]:
  """Our names of a LIBERO suite's tasks ("libero_object" -> "libero_object:0", ...), or one task's."""
  suite, _, which = name.partition(":")
  listed = tasks(_check_suite(suite))
  if not which:
    return tuple(f"{suite}:{t.index}" for t in listed)
  return (f"{suite}:{parse(name).index}",)


def parse(name: str) -> Task:
  """The task our name `<suite>:<index>` (or `<suite>:<LIBERO task name>`) stands for."""
  suite, sep, which = name.partition(":")
  if not sep or not which:
    raise ValueError(f"a LIBERO task is named <suite>:<index>, e.g. libero_object:3; got {name!r}")
  return task(_check_suite(suite), int(which) if which.isdigit() else which)


# The suites' names in the paper's and the field's tables (LIBERO-10 is "LIBERO-Long"), and the
# letter our per-task columns use: O3 is LIBERO-Object's task 3.
TITLES = {"libero_spatial": "Spatial", "libero_object": "Object", "libero_goal": "Goal", "libero_10": "Long",
          "libero_90": "90"}
_LETTERS = {"libero_spatial": "S", "libero_object": "O", "libero_goal": "G", "libero_10": "L", "libero_90": "N"}


def abbr(name: str) -> str:
  """A LIBERO task's column heading: its suite's letter and its index ("libero_object:3" -> "O3")."""
  suite, _, which = name.partition(":")
  return f"{_LETTERS[_check_suite(suite)]}{which}"

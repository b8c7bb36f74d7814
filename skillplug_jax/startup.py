"""What `make` gives a process, given to one started directly: glibc's allocator setting.

The Makefile exports GLIBC_TUNABLES=glibc.malloc.hugetlb=1 (XLA:CPU's
per-call buffers on huge pages: a paper-shape train step in about 0.7x the
time, docs/development.md). glibc reads it once, when the process starts, so
setting os.environ later does nothing: an entry point (the `skillplug`
command, `python -m experiments...`, `benchmarks...`, `figures...`,
notebooks/execute.py) calls `prepare_process` before any work, which
replaces the process (same pid, same arguments) by one started with it.

A value the user set, even an empty one, is kept. Nothing happens outside
Linux with glibc, inside pytest, or when the package is imported as a
library (a notebook kernel cannot be restarted from inside: start Jupyter
with the variable exported). MUJOCO_GL needs no restart: envs/headless.py
sets it at import.
"""

from __future__ import annotations

import os
import sys

TUNABLES = "glibc.malloc.hugetlb=1"  # the Makefile's (tests/test_headless.py holds them equal)
_RESTARTED = "SKILLPLUG_RESTARTED_WITH_TUNABLES"  # set across the exec: never a second one


def _glibc() -> bool:
  try:
    return sys.platform.startswith("linux") and os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc")
  except (ValueError, OSError, AttributeError):
    return False


def prepare_process() -> None:
  """Restart this process once with GLIBC_TUNABLES set, when it is unset (call it first)."""
  if ("GLIBC_TUNABLES" in os.environ or os.environ.get(_RESTARTED) or "pytest" in sys.modules
      or not _glibc() or not sys.executable or not getattr(sys, "orig_argv", None)):
    return
  env = {**os.environ, "GLIBC_TUNABLES": TUNABLES, _RESTARTED: "1"}
  sys.stdout.flush()
  sys.stderr.flush()
  os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)


def prepare_if_run_as_module() -> None:
  """`prepare_process`, when this package's __init__ runs because of `python -m package.module`
  (Python sets sys.argv[0] to '-m' until it has found the module), not at a library import."""
  if sys.argv[:1] == ["-m"]:
    prepare_process()


def cpu_name() -> str:
  """'<model name>, family F model M' from /proc/cpuinfo: the machine that timings and results
  name (the one implementation: benchmarks and the pipeline's summaries)."""
  try:
    with open("/proc/cpuinfo") as f:
      first = f.read().split("\n\n")[0]
    info = dict(line.split(":", 1) for line in first.splitlines() if ":" in line)
  except OSError:
    return "unknown"
  info = {k.strip(): v.strip() for k, v in info.items()}
  return f"{info.get('model name', '?')}, family {info.get('cpu family', '?')} model {info.get('model', '?')}"

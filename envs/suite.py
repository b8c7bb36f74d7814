"""The suite itself, loaded by `import envs` when first used (`envs.__getattr__`): the tasks,
tasksets, `make` and the batch classes. Use it as `envs.make`, `envs.TASKS`, ...
"""

from __future__ import annotations

import jax.numpy as jnp

from envs import appearance as appearance_module
from envs import batched, mujoco_batch
from envs.batched import BatchedEnv
from envs.env import EnvConfig, TabletopEnv
from envs.mujoco_batch import MujocoBatchEnv
from envs.names import OBJECT_STATE_DIM, check_backend, resolve_backend
from envs.tasks.block_bridge_place import BlockBridgePlace
from envs.tasks.block_place import BlockPlace
from envs.tasks.coffeecup_place import CoffeecupPlace
from envs.tasks.cuplid_cover import CuplidCover
from envs.tasks.drawer_open import DrawerOpen
from envs.tasks.jujube_pick import JujubePick
from envs.tasks.jujube_place import JujubePlace
from envs.tasks.kiwi_place import KiwiPlace
from envs.tasks.laptop_close import LaptopClose
from envs.tasks.mouse_push import MousePush
from envs.tasks.stack_block import StackBlock

TASKS: dict[str, type[TabletopEnv]] = {
    cls.name: cls for cls in (
        JujubePick, KiwiPlace, StackBlock, CoffeecupPlace, BlockBridgePlace, DrawerOpen,
        LaptopClose, CuplidCover, BlockPlace, JujubePlace, MousePush)
}

TASKSETS: dict[str, tuple[str, ...]] = {
    # The paper's table order.
    "discoverse7": ("jujube_pick", "kiwi_place", "stack_block", "coffeecup_place",
                    "block_bridge_place", "drawer_open", "laptop_close"),
    "discoverse_fewshot4": ("cuplid_cover", "block_place", "jujube_place", "mouse_push"),
    # The CPU quickstart's pretraining set: the discoverse7 tasks whose expert
    # episodes and time limits are shortest, so closed-loop evaluation is quick.
    "quickstart3": ("jujube_pick", "drawer_open", "laptop_close"),
}



def padded_object_state(x):
  """Zero-pad object state (last axis) to OBJECT_STATE_DIM."""
  pad = OBJECT_STATE_DIM - x.shape[-1]
  if pad < 0:
    raise ValueError(f"object state has width {x.shape[-1]} > OBJECT_STATE_DIM={OBJECT_STATE_DIM}")
  return jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, pad)])


def task_class(name: str) -> type[TabletopEnv]:
  from envs.libero import suites as libero_suites
  if name not in TASKS and libero_suites.is_libero(name):
    raise ValueError(f"{name} is a LIBERO task: it runs on envs.libero's engine (engine.LiberoBatch, LIBERO's "
                     "actions), not envs.make; closed-loop evaluation of policies on LIBERO is not built yet")
  if name not in TASKS:
    raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(TASKS)}")
  return TASKS[name]


def quiet_warp() -> None:
  """Silence Warp's per-module compile and cache messages (warnings still print)."""
  import warp as wp
  wp.config.quiet = True
  wp.config.log_level = wp.LOG_WARNING


def taskset(name: str) -> tuple[str, ...]:
  """Task names of a taskset; a single task name is accepted as a one-task set. LIBERO's suites
  (libero_spatial, libero_object, libero_goal, libero_10, libero_90) name their tasks
  "<suite>:<index>" (`envs.libero.suites.taskset`)."""
  if name in TASKSETS:
    return TASKSETS[name]
  if name in TASKS:
    return (name,)
  from envs.libero import suites as libero_suites  # cheap: LIBERO itself loads only for its suites
  if libero_suites.is_libero(name):
    return libero_suites.taskset(name)
  raise ValueError(
      f"unknown taskset {name!r}; valid tasksets: {', '.join(TASKSETS)}, {', '.join(libero_suites.SUITES)} "
      f"(or one task: {', '.join(TASKS)}, or <libero suite>:<index>)")


def renderer_of(backend: str) -> str:
  """The renderer that draws a backend's camera images (they differ pixel by pixel)."""
  return mujoco_batch.RENDERER if check_backend(backend, "envs.renderer_of") == "mujoco" else batched.RENDERER


def make(name: str, num_envs: int = 1, render: bool = False, image_size=(64, 64),
         backend: str = "auto", devices: tuple | None = None, appearance: str = "default",
         **config) -> BatchedEnv | MujocoBatchEnv:
  """A batch of `num_envs` environments of task `name` (per device, when rendering on `devices`).

  image_size: (H, W) of both cameras' images, as everywhere in the project.
  appearance: "default", or "shifted": the cameras see other colours and
  light, drawn per environment from its reset key (`envs.appearance`).
  """
  if num_envs < 1:
    raise ValueError(f"num_envs must be >= 1, got {num_envs}")
  appearance_module.check(appearance)
  env = task_class(name)(EnvConfig(backend=resolve_backend(backend), num_envs=num_envs, **config))
  return batch_of(env, num_envs, render=render, image_size=image_size, devices=devices, appearance=appearance)


def batch_of(env: TabletopEnv, num_envs: int, render: bool = False, image_size=(64, 64),
             devices: tuple | None = None, appearance: str = "default") -> BatchedEnv | MujocoBatchEnv:
  """A batch of `num_envs` copies of `env` on the backend it was made for."""
  if env.backend == "mujoco":
    if devices is not None and len(devices) > 1:
      raise ValueError("the 'mujoco' backend runs on the CPU's threads: it takes no devices")
    return MujocoBatchEnv(env, num_envs, render=render, image_size=image_size, appearance=appearance)
  return BatchedEnv(env, num_envs, render=render, image_size=image_size, devices=devices, appearance=appearance)

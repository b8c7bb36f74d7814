"""The suite's names, defined once and cheap to import: configs check their settings against
them without loading MuJoCo or the tasks (`import envs.names` runs only envs/__init__.py's
GL choice, see `envs.__getattr__`).

The physics backend is "mujoco" (MuJoCo's C engine, for CPUs) or "mjx-warp" (MJX on MuJoCo
Warp, for accelerators). A setting may also say "auto", which `resolve_backend` turns into one
of the two where a command or an API call starts (the CLI's commands, the pipeline, `envs.make`,
`DemoConfig`, `loop.train`, the evaluation and few-shot entry points); the layers below take the
concrete name and reject "auto" (`check_backend`).
"""

from __future__ import annotations

ENGINES = ("mujoco", "mjx-warp")  # the physics backends themselves
BACKENDS = ("auto",) + ENGINES  # what a setting or a --backend flag may name
# The cameras envs/robot.py's arm defines (a side camera on the world, a wrist camera on the
# gripper), in the order images are recorded, stacked and fed to policies.
CAMERAS = ("side", "wrist")
# Privileged object state is padded to this width so that one state-based
# policy can read every task: block bridge, the widest, has four free objects
# of 7 numbers each. Datasets and policies are built with this width, so a task
# that needs more is an error (tests/test_tasks.py checks every task fits).
OBJECT_STATE_DIM: int = 28


class UnresolvedBackend(ValueError):
  """A layer below the edges was handed backend "auto": it is resolved once, where the command
  or API call starts (`resolve_backend`), and passed down as "mujoco" or "mjx-warp"."""


def _unknown(name) -> ValueError:
  return ValueError(f"unknown backend {name!r}; valid backends: {', '.join(BACKENDS)}")


def resolve_backend(name: str) -> str:
  """'auto' is MJX-Warp when JAX sees a GPU and MuJoCo's C engine otherwise,
  which on a CPU steps our tasks about 60x faster than Warp (docs/measurements/physics_backends.md).
  The one place "auto" is resolved; called where a command or API call starts."""
  if name not in BACKENDS:
    raise _unknown(name)
  if name == "auto":
    import jax  # here, not at import: the names stay cheap, and jax.distributed may start first
    return "mjx-warp" if jax.default_backend() == "gpu" else "mujoco"
  return name


def check_backend(name: str, where: str) -> str:
  """`name` if it is a concrete backend; "auto" raises `UnresolvedBackend` naming `where`."""
  if name == "auto":
    raise UnresolvedBackend(f"{where} takes a resolved backend ({' or '.join(ENGINES)}), not 'auto': "
                            "resolve it where the command or API call starts (envs.resolve_backend)")
  if name not in ENGINES:
    raise _unknown(name)
  return name


# LIBERO's observations as our datasets and policies name them (envs/libero/layout.py says what each
# holds): its cameras, and its proprioception fields with their widths.
LIBERO_CAMERAS = ("agentview", "eye_in_hand")
LIBERO_PROPRIO = (("joint_pos", 7), ("gripper_qpos", 2), ("eef_pos", 3), ("eef_quat", 4))

"""The tabletop environment: Brax's Env/State API over an MJX model.

One class holds what every task shares (robot, control at 20 Hz over physics
substeps, observations, NaN handling); a task subclasses it with its objects,
reset sampler, success predicate and scripted expert plan. Everything here
acts on a single environment and is pure, so batching is `jax.vmap` (see
`envs.batched`), as in Brax and MuJoCo Playground.

The physics runs on one of two backends (`EnvConfig.backend`): `mjx-warp`
(MJX on MuJoCo Warp, this class's own `reset`/`step`, for accelerators) or
`mujoco` (MuJoCo's C engine through `mujoco.batch`, `envs.mujoco_batch`, for
CPUs). Task logic is written once, as pure functions of the state arrays
(`qpos`, `xpos`, `sensordata`, ...), and `first_state` / `next_state` turn
either engine's arrays into the same Brax `State`.

Success is declared, and the episode ends, once the task's predicate has held
for `SUCCESS_HOLD_STEPS` consecutive control steps: DISCOVERSE checks its
conditions once, after its expert has released and retreated; checked every
step, a state that passes for an instant (an object dropped through its
target, a stack knocked over) must not count. `first_success_step` is the
first step of that run.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from mujoco import mjx
from mujoco.mjx.third_party import mujoco_warp as mjw

from envs import robot, scene
from envs.names import BACKENDS, check_backend  # noqa: F401 (envs.env.BACKENDS)

SUCCESS_HOLD_STEPS = 10  # 0.5 s at 20 Hz
# The gripper: every body whose contact with an object means "still held".
GRIPPER_SUBTREE = "link6"
# MuJoCo Warp's per-world overflow bits that mean the constraint solver or its
# line search stopped at its iteration limit (the step is still usable, only
# less exact). They are counted per episode instead of printed per step.
SOLVER_LIMIT_BITS = {"solver_iterations": int(mjw.OverflowType.ITERATIONS),
                     "linesearch_iterations": int(mjw.OverflowType.LS_ITERATIONS)}


@dataclasses.dataclass(frozen=True)
class EnvConfig:
  """Physics and observation settings shared by all tasks."""
  backend: str  # "mujoco" or "mjx-warp" (envs.names.ENGINES); `envs.make` resolves "auto"
  control_dt: float = scene.CONTROL_DT
  physics_timestep: float = scene.PHYSICS_TIMESTEP
  num_envs: int = 1  # contact buffers are sized for this many worlds
  contacts_per_env: int = 48
  constraints_per_env: int = 256


@dataclasses.dataclass(frozen=True)
class Phase:
  """One state of a scripted expert: a joint-space goal latched on entry.

  goal: fn(env, data) -> 7-D joint target (arm + finger opening), read from
    privileged object poses when the phase starts.
  min_steps: control steps to stay at least (lets the gripper close or open).
  tol: arm joint error (rad) under which the goal counts as reached.
  """
  goal: callable
  min_steps: int = 0
  tol: float = 0.01


class TabletopEnv(Env):
  """Base class of the 11 DISCOVERSE-style tasks."""

  name: str = ""
  abbr: str = ""
  time_limit_s: float = 10.0
  objects: Sequence[str] = ()  # free bodies, in privileged-state order
  extra_joints: Sequence[str] = ()  # articulated objects' joints (drawer, lid)

  def __init__(self, config: EnvConfig):
    check_backend(config.backend, f"{type(self).__name__}(EnvConfig(backend=...))")
    self.config = config
    xml = scene.model_xml(self.name, self.objects_xml(), sensors=self._gripper_contact_sensors())
    m = scene.compile_model(xml)
    m.opt.timestep = config.physics_timestep
    self.mj_model = m
    self.mjx_model = None  # the C engine needs no MJX model
    if config.backend == "mjx-warp":
      self.mjx_model = _without_solver_limit_prints(mjx.put_model(m, impl="warp"))
    self.n_substeps = int(round(config.control_dt / config.physics_timestep))
    self._body = {m.body(i).name: i for i in range(m.nbody)}
    self._site = {m.site(i).name: i for i in range(m.nsite)}
    self._qadr = {m.joint(i).name: int(m.jnt_qposadr[i]) for i in range(m.njnt)}
    self._touch_adr = {b: int(m.sensor(f"gripper_touches_{b}").adr[0]) for b in self.objects}

  # ---- what a task provides -------------------------------------------------
  def objects_xml(self) -> str:
    raise NotImplementedError(f"{type(self).__name__} defines no objects")

  def _gripper_contact_sensors(self) -> str:
    """One MuJoCo contact sensor per object: how many gripper contacts touch it."""
    return "".join(
        f'<contact name="gripper_touches_{b}" subtree1="{GRIPPER_SUBTREE}" body2="{b}" data="found" num="1"/>'
        for b in self.objects)

  def sample_objects(self, key, qpos):
    """Return qpos with the objects placed by the task's randomisation."""
    return qpos

  def success(self, data) -> jax.Array:
    """The completion predicate: True in a state where the task is done."""
    raise NotImplementedError

  def expert_plan(self) -> Sequence[Phase]:
    raise NotImplementedError

  # ---- helpers for tasks ----------------------------------------------------
  def pos(self, data, body):
    return data.xpos[self._body[body]]

  def mat(self, data, body):
    return data.xmat[self._body[body]]

  def qpos_of(self, data, joint):
    return data.qpos[self._qadr[joint]]

  def grasp_pos(self, data):
    return data.site_xpos[self._site["grasp"]]

  def released(self, data, *bodies):
    """No part of the gripper touches any of `bodies` (MuJoCo contact sensors).

    Sensors are evaluated in the last substep's forward pass, 5 ms before the
    state they come with: negligible against the 0.5 s hold.
    """
    return jnp.all(jnp.stack([data.sensordata[self._touch_adr[b]] == 0 for b in bodies]))

  def place(self, qpos, body, xyz, yaw=0.0):
    """Set a free body's pose in qpos (position and yaw about z)."""
    a = self._qadr[body]
    quat = jnp.array([jnp.cos(yaw / 2), 0.0, 0.0, jnp.sin(yaw / 2)])
    return qpos.at[a:a + 3].set(jnp.asarray(xyz)).at[a + 3:a + 7].set(quat)

  def nominal(self, body):
    """A free body's position as written in the MJCF."""
    return jnp.asarray(self.mj_model.body(body).pos)

  # ---- Brax Env API ---------------------------------------------------------
  @property
  def episode_length(self) -> int:
    return int(round(self.time_limit_s / self.config.control_dt))

  @property
  def observation_size(self):
    return {"joint_pos": robot.ACTION_DIM, "object_state": 7 * len(self.objects) + len(self.extra_joints)}

  @property
  def action_size(self) -> int:
    return robot.ACTION_DIM

  @property
  def backend(self) -> str:  # an abstract property of Brax's Env
    return self.config.backend

  # ---- the episode's bookkeeping, on either backend's state arrays ----------
  def initial_qpos(self, rng: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(qpos, ctrl) of a reset: the arm at home, the objects sampled from `rng`."""
    qpos = jnp.asarray(self.mj_model.qpos0, jnp.float32)
    qpos = qpos.at[:robot.ARM_DOF].set(robot.HOME_QPOS[:robot.ARM_DOF])
    qpos = qpos.at[robot.ARM_DOF:robot.ARM_DOF + 2].set(robot.HOME_QPOS[robot.ARM_DOF])
    qpos = self.sample_objects(rng, qpos)
    return qpos, robot.action_to_ctrl(jnp.asarray(robot.HOME_QPOS, jnp.float32))

  def first_state(self, data) -> State:
    """The State of a reset, from the physics after its forward pass."""
    zero = jnp.zeros(())
    metrics = {"success": zero, "nan": zero, "overflow": _overflow(data)}
    info = {"first_success_step": jnp.full((), -1, jnp.int32), "t": jnp.zeros((), jnp.int32),
            "held": jnp.zeros((), jnp.int32)}
    return State(pipeline_state=data, obs=self.observation(data), reward=zero,
                 done=zero, metrics=metrics, info=info)

  def next_state(self, state: State, data, failed, keep=None) -> State:
    """The State after one control step whose physics ended in `data`.

    failed: the physics blew up (NaN, or the C engine's instability warning):
      the episode fails alone, keeping its last good state.
    keep: also keep the previous physics (default: where failed), as for an
      episode that has ended and was not simulated.
    """
    prev = state.pipeline_state
    keep = failed if keep is None else keep
    data = data.where(keep, prev)
    ok = self.success(data) & ~failed
    t = state.info["t"] + 1
    held = jnp.where(ok, state.info["held"] + 1, 0)
    declared = (held >= SUCCESS_HOLD_STEPS) & (state.info["first_success_step"] < 0)
    first = jnp.where(declared, t - SUCCESS_HOLD_STEPS + 1, state.info["first_success_step"])
    solved = (first >= 0).astype(jnp.float32)
    done = jnp.maximum(state.done, jnp.maximum(solved, failed.astype(jnp.float32)))
    metrics = {"success": solved, "nan": jnp.maximum(state.metrics["nan"], failed.astype(jnp.float32)),
               "overflow": state.metrics["overflow"] | _overflow(data)}
    info = {**state.info, "first_success_step": first, "t": t, "held": held}
    return state.replace(pipeline_state=data, obs=self.observation(data),
                         reward=declared.astype(jnp.float32), done=done, metrics=metrics, info=info)

  # ---- Brax Env API on MJX-Warp (the C engine: envs.mujoco_batch) ------------
  def reset(self, rng: jax.Array) -> State:
    c = self.config
    data = mjx.make_data(self.mj_model, impl="warp", naconmax=c.num_envs * c.contacts_per_env,
                         njmax=c.constraints_per_env)
    qpos, ctrl = self.initial_qpos(rng)
    return self.first_state(mjx.forward(self.mjx_model, data.replace(qpos=qpos, ctrl=ctrl)))

  def step(self, state: State, action: jax.Array) -> State:
    check_action(self.name, action)
    data = state.pipeline_state.replace(ctrl=clipped_ctrl(action))
    data = jax.lax.fori_loop(0, self.n_substeps, lambda _, d: mjx.step(self.mjx_model, d), data)
    nan = ~(jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel)))
    return self.next_state(state, data, nan)

  def observation(self, data):
    q = data.qpos
    joint_pos = jnp.concatenate([q[:robot.ARM_DOF], q[robot.ARM_DOF:robot.ARM_DOF + 1]])
    return {"joint_pos": joint_pos, "object_state": self.object_state(data)}

  def object_state(self, data):
    """Privileged object state: each object's position and quaternion, then articulation angles."""
    parts = [jnp.concatenate([data.xpos[self._body[b]], data.xquat[self._body[b]]]) for b in self.objects]
    parts += [data.qpos[self._qadr[j]][None] for j in self.extra_joints]
    return jnp.concatenate(parts) if parts else jnp.zeros((0,))


def check_action(task: str, action) -> None:
  if action.shape[-1] != robot.ACTION_DIM:
    raise ValueError(
        f"{task}: action has dimension {action.shape[-1]}, expected "
        f"{robot.ACTION_DIM} (6 joint targets + gripper opening)")


def clipped_ctrl(action):
  """Actuator controls of a 7-D action, clipped to the joint ranges."""
  lo, hi = robot.JOINT_RANGES[:, 0], robot.JOINT_RANGES[:, 1]
  return robot.action_to_ctrl(jnp.clip(action, lo, hi))


def _without_solver_limit_prints(mx):
  """Stop MuJoCo Warp printing a line per world and step when the solver or its
  line search hits its iteration limit; the overflow bits still record it.
  Overflows that corrupt the physics (dropped contacts or constraints) still print."""
  impl = getattr(mx.opt, "_impl", None)
  if impl is None or not hasattr(impl, "warn_overflow"):
    return mx  # the JAX implementation prints nothing per step
  quiet = int(impl.warn_overflow) & ~sum(SOLVER_LIMIT_BITS.values())
  return mx.replace(opt=mx.opt.replace(_impl=impl.replace(warn_overflow=quiet)))


def _overflow(data):
  """The physics' overflow bitmask (Warp's, or the C engine's `PhysicsState.overflow`)."""
  impl = getattr(data, "_impl", None)  # mjx.Data's (reading data.overflow itself is deprecated)
  bits = getattr(impl, "overflow", None) if impl is not None else getattr(data, "overflow", None)
  return jnp.zeros((), jnp.int32) if bits is None else jnp.asarray(bits, jnp.int32).reshape(())


def solver_limit_counts(overflow) -> dict:
  """Episodes (of a batch's overflow bitmasks) whose solver or line search hit its limit."""
  bits = np.asarray(overflow).astype(np.int64)
  return {name: int(((bits & bit) != 0).sum()) for name, bit in SOLVER_LIMIT_BITS.items()}

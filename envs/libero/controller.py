"""LIBERO's action interface, batched: robosuite 1.4.0's OSC_POSE controller and the Panda gripper.

A LIBERO action is 7 numbers in [-1, 1]: an end-effector position delta (scaled to +-5 cm), an
axis-angle orientation delta (+-0.5 rad) and the gripper (-1 open, +1 close). At each 20 Hz
control step robosuite sets a goal pose from the action and the end effector's pose; then at
each of the 25 physics substeps it recomputes joint torques from the state (operational-space
control: the pose error through the task-space inertia, gravity and Coriolis compensation, a
nullspace pull toward the robot's initial joints) and moves the gripper's position targets a
little toward the commanded side. We reimplement exactly that, over B environments, from the
arrays a MuJoCo engine gives after a forward pass; parameters come from the reference env when
a scene is built (`params_of`), so nothing here is a copy of robosuite's numbers.

Every function takes the array namespace `xp` (numpy for MuJoCo's C engine, in float64 as
robosuite computes; jax.numpy for MJX), so both backends run one source of control logic.

State carried between control steps (`ControlState`): the goal orientation, because robosuite
keeps the previous one when an action's rotation is exactly zero (its first goal is the end
effector's orientation at the robot's reset pose, not at the init state), and the gripper's
integrated command.

One quirk of the reference matters from the first step: robosuite's controller caches what it
reads of the robot and refreshes it only after computing torques. env.reset() fills that cache
with the robot at its reset pose, and LIBERO's set_init_state does not refresh it, so the
first control step of every LIBERO trial sets its goal position from the reset pose's end
effector (plus the action's delta) and computes its first substep's torques from the reset
pose's kinematics (with the current gravity compensation, which is read live). The engine
reproduces it (`engine.LiberoBatch.reset`); without it a trajectory departs by millimetres
in the first step.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

NULLSPACE_KP = 10.0  # robosuite's nullspace_torques default (joint_kp), not configurable there


@dataclasses.dataclass(frozen=True)
class OscParams:
  """The controller and gripper as the reference env configures them (arrays as tuples, hashable)."""
  kp: tuple  # [6] position then orientation stiffness
  kd: tuple  # [6]
  input_min: tuple  # [6]
  input_max: tuple
  output_min: tuple
  output_max: tuple
  torque_min: tuple  # [7] the arm actuators' ctrlrange
  torque_max: tuple
  initial_joint: tuple  # [7] the nullspace target: the robot's reset pose
  initial_goal_ori: tuple  # [3][3] the end effector's orientation at that pose
  gripper_speed: float  # of the integrated command, per physics substep
  gripper_init_qpos: tuple  # [2] the fingers' joints at the robot's reset pose
  gripper_ctrl_min: tuple  # [2] the finger actuators' ctrlrange
  gripper_ctrl_max: tuple
  arm_actuators: tuple  # actuator ids of the 7 joint torques
  gripper_actuators: tuple  # actuator ids of the 2 finger position servos
  arm_qpos: tuple  # qpos addresses of the arm joints
  arm_dofs: tuple  # their dof addresses
  eef_site: int
  substeps: int  # physics steps per control step


class ControlState(NamedTuple):
  goal_ori: object  # [B, 3, 3]
  gripper: object  # [B, 2] integrated finger command in [-1, 1]


class ArmState(NamedTuple):
  """What the controller reads of the physics after a forward pass, batched."""
  ee_pos: object  # [B, 3] the end-effector site
  ee_mat: object  # [B, 3, 3]
  jac: object  # [B, 6, 7] translational then rotational Jacobian of the site on the arm's dofs
  mass: object  # [B, 7, 7] the arm's block of the joint-space inertia
  bias: object  # [B, 7] Coriolis, centrifugal and gravity forces (qfrc_bias)
  q: object  # [B, 7]
  dq: object  # [B, 7]


def params_of(env) -> dict:
  """The controller's parameters from a LIBERO reference env (after its reset), as JSON for the
  scene's metadata. Fails if the env is configured other than how LIBERO evaluates (OSC_POSE,
  fixed impedance, delta control, no interpolation or limits), which this module does not model."""
  inner = env.env
  robot = inner.robots[0]
  c = robot.controller
  checks = {"controller": (type(c).__name__, "OperationalSpaceController"), "impedance_mode": (c.impedance_mode, "fixed"),
            "control_ori": (c.use_ori, True), "control_delta": (c.use_delta, True), "uncouple_pos_ori": (c.uncoupling, True),
            "interpolator": ((c.interpolator_pos, c.interpolator_ori), (None, None)),
            "limits": ((c.position_limits, c.orientation_limits), (None, None)),
            "gripper": (type(robot.gripper).__name__, "PandaGripper")}
  wrong = {k: got for k, (got, want) in checks.items() if got != want}
  if wrong:
    raise RuntimeError(f"the reference env's controller is not LIBERO's OSC_POSE as envs/libero/controller.py models it: {wrong}")
  model = inner.sim.model._model
  gripper_ids = [model.actuator(name).id for name in robot.gripper.actuators]
  steps = inner.control_timestep / inner.model_timestep
  if abs(steps - round(steps)) > 1e-9:
    raise RuntimeError(f"control step {inner.control_timestep} s is not a whole number of physics steps")
  floats = lambda a: [float(v) for v in np.ravel(a)]  # noqa: E731
  return {
    "kp": floats(c.kp), "kd": floats(c.kd), "input_min": floats(c.input_min), "input_max": floats(c.input_max),
    "output_min": floats(c.output_min), "output_max": floats(c.output_max),
    "torque_min": floats(robot.torque_limits[0]), "torque_max": floats(robot.torque_limits[1]),
    "initial_joint": floats(c.initial_joint), "initial_goal_ori": np.asarray(c.initial_ee_ori_mat, float).tolist(),
    "gripper_speed": float(robot.gripper.speed), "gripper_init_qpos": floats(robot.gripper.init_qpos),
    "gripper_ctrl_min": floats(model.actuator_ctrlrange[gripper_ids, 0]),
    "gripper_ctrl_max": floats(model.actuator_ctrlrange[gripper_ids, 1]),
    "arm_actuators": [int(i) for i in robot._ref_joint_actuator_indexes], "gripper_actuators": gripper_ids,
    "arm_qpos": [int(i) for i in c.qpos_index], "arm_dofs": [int(i) for i in c.qvel_index],
    "eef_site": int(model.site(c.eef_name).id), "substeps": int(round(steps))}


def params(meta: dict) -> OscParams:
  """`OscParams` from a scene's metadata (`params_of`'s dict under meta["controller"])."""
  c = meta["controller"]
  tup = lambda v: tuple(tuple(r) if isinstance(r, list) else r for r in v)  # noqa: E731
  return OscParams(**{f.name: tup(c[f.name]) if isinstance(c[f.name], list) else c[f.name]
                      for f in dataclasses.fields(OscParams)})


def initial_state(p: OscParams, batch: int, xp=np) -> ControlState:
  """The controller's state at the start of a LIBERO trial (after env.reset(), set_init_state)."""
  ori = xp.broadcast_to(xp.asarray(p.initial_goal_ori, dtype=float), (batch, 3, 3))
  return ControlState(goal_ori=xp.array(ori), gripper=xp.zeros((batch, 2)))


def _axis_angle_matrix(v, xp):
  """Rotation matrices [B, 3, 3] of axis-angle vectors [B, 3] (Rodrigues); identity at zero, as
  robosuite's axisangle2quat gives."""
  angle = xp.linalg.norm(v, axis=-1)
  safe = xp.where(angle > 0, angle, 1.0)
  k = v / safe[:, None]
  zero = xp.zeros_like(angle)
  kx = xp.stack([xp.stack([zero, -k[:, 2], k[:, 1]], -1), xp.stack([k[:, 2], zero, -k[:, 0]], -1),
                 xp.stack([-k[:, 1], k[:, 0], zero], -1)], -2)
  s, c = xp.sin(angle)[:, None, None], xp.cos(angle)[:, None, None]
  eye = xp.eye(3)[None]
  rot = eye + s * kx + (1 - c) * (kx @ kx)
  return xp.where((angle > 0)[:, None, None], rot, eye)


def scale(p: OscParams, action, xp=np):
  """The arm's 6 action numbers clipped to the input range and mapped onto the output range."""
  lo, hi = xp.asarray(p.input_min), xp.asarray(p.input_max)
  out_lo, out_hi = xp.asarray(p.output_min), xp.asarray(p.output_max)
  ratio = xp.abs(out_hi - out_lo) / xp.abs(hi - lo)
  return (xp.clip(action, lo, hi) - (hi + lo) / 2) * ratio + (out_hi + out_lo) / 2


def set_goal(p: OscParams, state: ControlState, arm: ArmState, action, xp=np):
  """The goal pose of a control step (robosuite's set_goal): position = the site's + the delta; the
  orientation rotated from the site's by the delta, or the previous goal's where the delta's
  rotation is exactly zero. Returns (goal_pos [B, 3], new ControlState)."""
  delta = scale(p, action[:, :6], xp)
  turn = xp.any(delta[:, 3:] != 0, axis=-1)
  rotated = _axis_angle_matrix(delta[:, 3:], xp) @ arm.ee_mat
  goal_ori = xp.where(turn[:, None, None], rotated, state.goal_ori)
  return arm.ee_pos + delta[:, :3], state._replace(goal_ori=goal_ori)


def orientation_error(desired, current, xp=np):
  """robosuite's orientation_error: half the sum of the cross products of matching columns."""
  return 0.5 * sum(xp.cross(current[:, :, i], desired[:, :, i]) for i in range(3))


def torques(p: OscParams, goal_pos, goal_ori, arm: ArmState, xp=np):
  """Joint torques [B, 7] of one physics substep (robosuite's run_controller and SingleArm.control:
  clipped to the actuators' torque limits)."""
  kp, kd = xp.asarray(p.kp), xp.asarray(p.kd)
  vel = xp.einsum("bij,bj->bi", arm.jac, arm.dq)  # the site's linear and angular velocity
  force = (goal_pos - arm.ee_pos) * kp[:3] - vel[:, :3] * kd[:3]
  moment = orientation_error(goal_ori, arm.ee_mat, xp) * kp[3:] - vel[:, 3:] * kd[3:]
  m_inv = xp.linalg.inv(arm.mass)
  jt = xp.swapaxes(arm.jac, -1, -2)
  lam_full = xp.linalg.pinv(arm.jac @ m_inv @ jt)
  lam_pos = xp.linalg.pinv(arm.jac[:, :3] @ m_inv @ jt[:, :, :3])
  lam_ori = xp.linalg.pinv(arm.jac[:, 3:] @ m_inv @ jt[:, :, 3:])
  wrench = xp.concatenate([xp.einsum("bij,bj->bi", lam_pos, force), xp.einsum("bij,bj->bi", lam_ori, moment)], -1)
  tau = xp.einsum("bji,bj->bi", arm.jac, wrench) + arm.bias
  jbar = m_inv @ jt @ lam_full
  nullspace = xp.eye(arm.q.shape[-1])[None] - jbar @ arm.jac
  kv = np.sqrt(NULLSPACE_KP) * 2
  pose = xp.einsum("bij,bj->bi", arm.mass, NULLSPACE_KP * (xp.asarray(p.initial_joint) - arm.q) - kv * arm.dq)
  tau = tau + xp.einsum("bji,bj->bi", nullspace, pose)
  return xp.clip(tau, xp.asarray(p.torque_min), xp.asarray(p.torque_max))


def gripper(p: OscParams, state: ControlState, command, xp=np):
  """One substep of the Panda gripper (PandaGripper.format_action, grip_action): the integrated
  command moves by `speed` toward closed (+1) or open (-1), then maps onto the fingers' ctrlrange.
  Returns (finger ctrl [B, 2], new ControlState)."""
  step = xp.asarray([-1.0, 1.0]) * p.gripper_speed * xp.sign(command)[:, None]
  g = xp.clip(state.gripper + step, -1.0, 1.0)
  lo, hi = xp.asarray(p.gripper_ctrl_min), xp.asarray(p.gripper_ctrl_max)
  return (hi + lo) / 2 + (hi - lo) / 2 * g, state._replace(gripper=g)

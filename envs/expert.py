"""Scripted experts: a state machine over privileged object poses, in pure JAX.

A task lists its phases (`envs.env.Phase`); each phase's joint goal comes from
closed-form IK on object poses read when the phase starts, and is held (latched)
for the phase. The command moves towards the goal in joint space at a bounded
speed, all arm joints arriving together; the phase ends when the arm is within
`tol` of the goal, nearly still, and has stayed `min_steps`. This mirrors the
DISCOVERSE experts (0.75 rad/s, 0.03 rad), with a faster joint speed and a
tighter tolerance so that placements are precise and long tasks fit their
time limits.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from envs import robot

JOINT_SPEED = 1.0  # rad/s for the arm
GRIPPER_SPEED = 0.2  # m/s per finger
STILL = 0.15  # rad/s: "nearly still"


class ExpertState(NamedTuple):
  phase: jax.Array  # int32
  goal: jax.Array  # (7,) latched joint goal of the current phase
  command: jax.Array  # (7,) joint targets sent last step
  steps: jax.Array  # int32 control steps spent in the phase
  fresh: jax.Array  # bool: phase just entered, goal not yet latched


def init(env, state) -> ExpertState:
  q = state.obs["joint_pos"]
  return ExpertState(phase=jnp.zeros((), jnp.int32), goal=q, command=q,
                     steps=jnp.zeros((), jnp.int32), fresh=jnp.ones((), bool))


def act(env, data, xs: ExpertState):
  """One control step of the expert: (action, next expert state)."""
  phases = env.expert_plan()
  branches = [lambda d, p=p: jnp.asarray(p.goal(env, d), jnp.float32) for p in phases]
  goal = jnp.where(xs.fresh, jax.lax.switch(xs.phase, branches, data), xs.goal)
  tol = jnp.asarray([p.tol for p in phases])[xs.phase]
  min_steps = jnp.asarray([p.min_steps for p in phases])[xs.phase]

  dt = env.config.control_dt
  delta = goal - xs.command
  arm = delta[:robot.ARM_DOF]
  scale = jnp.minimum(1.0, JOINT_SPEED * dt / (jnp.max(jnp.abs(arm)) + 1e-9))
  grip = jnp.clip(delta[robot.ARM_DOF:], -GRIPPER_SPEED * dt, GRIPPER_SPEED * dt)
  command = xs.command + jnp.concatenate([arm * scale, grip])

  q = data.qpos[:robot.ARM_DOF]
  qd = data.qvel[:robot.ARM_DOF]
  reached = (jnp.all(jnp.abs(q - goal[:robot.ARM_DOF]) < tol)
             & jnp.all(jnp.abs(qd) < STILL)
             & jnp.all(jnp.abs(command - goal) < 1e-6))
  advance = reached & (xs.steps + 1 >= min_steps) & (xs.phase < len(phases) - 1)
  nxt = ExpertState(phase=xs.phase + advance.astype(jnp.int32), goal=goal, command=command,
                    steps=jnp.where(advance, 0, xs.steps + 1), fresh=advance)
  return command, nxt


# ---- phase goals shared by the tasks -------------------------------------------


def natural_yaw(p):
  """Closing-axis yaw that leaves joint6 at zero (perpendicular to the arm plane)."""
  return jnp.arctan2(p[1], p[0]) + jnp.pi / 2


def box_yaw(mat, p):
  """Closing-axis yaw aligned with a square box's faces, the one nearest natural_yaw."""
  yaw = jnp.arctan2(mat[1, 0], mat[0, 0])
  nat = natural_yaw(p)
  k = jnp.round((nat - yaw) / (jnp.pi / 2))
  return yaw + k * jnp.pi / 2


def top(p, yaw=None, opening=robot.GRIPPER_OPEN):
  """Tool pointing down, grasp point at p."""
  yaw = natural_yaw(p) if yaw is None else yaw
  return robot.grasp_joint_targets(p, yaw, robot.TOOL_DOWN, opening)


def pick_and_place(obj, target, *, grasp_dz=0.0, hover=0.08, place_dz=0.0,
                   grasp_yaw=None, place_yaw=None, opening=robot.GRIPPER_OPEN,
                   release_opening=None, close_steps=8):
  """Phases of a top-down pick of body `obj` and its release at `target`.

  target: fn(env, data) -> xyz where the object's origin should be released
    (corrected for where the object sits in the fingers, measured after the lift).
  grasp_yaw / place_yaw: fn(env, data) -> closing-axis yaw; default natural_yaw.
  """
  def obj_p(env, d):
    return env.pos(d, obj) + jnp.array([0.0, 0.0, grasp_dz])

  def yaw(env, d):
    return natural_yaw(env.pos(d, obj)) if grasp_yaw is None else grasp_yaw(env, d)

  def release_at(env, d):
    # Where the grasp point must go so that the held object lands on target.
    return target(env, d) + (env.grasp_pos(d) - env.pos(d, obj))

  def tgt_yaw(env, d):
    return natural_yaw(target(env, d)) if place_yaw is None else place_yaw(env, d)

  up = jnp.array([0.0, 0.0, hover])
  dz = jnp.array([0.0, 0.0, place_dz])
  closed = robot.GRIPPER_CLOSED
  release = opening if release_opening is None else release_opening
  return [
      _phase(lambda env, d: top(obj_p(env, d) + up, yaw(env, d), opening)),
      _phase(lambda env, d: top(obj_p(env, d), yaw(env, d), opening), tol=0.006),
      _phase(lambda env, d: top(obj_p(env, d), yaw(env, d), closed), min_steps=close_steps),
      _phase(lambda env, d: top(env.grasp_pos(d) + up, yaw(env, d), closed), tol=0.03),
      _phase(lambda env, d: top(release_at(env, d) + up, tgt_yaw(env, d), closed), tol=0.01),
      _phase(lambda env, d: top(release_at(env, d) + dz, tgt_yaw(env, d), closed), tol=0.005),
      _phase(lambda env, d: top(env.grasp_pos(d), tgt_yaw(env, d), release), min_steps=6),
      _phase(lambda env, d: top(env.grasp_pos(d) + up, tgt_yaw(env, d), release), tol=0.05),
  ]


def fixed_yaw(value):
  return lambda env, d: jnp.asarray(value, jnp.float32)


def face_yaw(body):
  """Closing axis on a box's faces, the choice nearest natural_yaw."""
  return lambda env, d: box_yaw(env.mat(d, body), env.pos(d, body))


def _phase(goal, min_steps=0, tol=0.01):
  from envs.env import Phase  # local: env imports nothing from here
  return Phase(goal=goal, min_steps=min_steps, tol=tol)

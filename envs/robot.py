"""A 6-DoF arm with a parallel gripper, modelled on the AIRBOT Play, from primitive geoms.

Joint layout (all revolute, then two coupled finger slides):
  joint1 yaw (z) -> joint2 shoulder pitch (y) -> joint3 elbow pitch (y)
  -> joint4 forearm roll (z) -> joint5 wrist pitch (y) -> joint6 tool roll (z)
With joint4 = 0 the arm is planar in the vertical plane at yaw joint1, which is
what the closed-form inverse kinematics below exploits: the scripted experts
only ever ask for a tool that points down (top grasps) or straight ahead
(handles), so a planar two-link solve plus a wrist angle covers them.

The 7-D action is absolute joint-position targets: 6 arm joints and the
opening of each finger in metres (0 = closed, 0.04 = open); one value drives
both finger actuators so the gripper stays symmetric.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from envs.names import CAMERAS  # noqa: F401 (envs.robot.CAMERAS: the cameras `arm_mjcf` defines)

# Kinematic constants (metres). The MJCF below is written from these, so the
# inverse kinematics and the model cannot drift apart.
SHOULDER_HEIGHT = 0.12
UPPER_ARM = 0.28
FOREARM = 0.26
FOREARM_ROLL_OFFSET = 0.05  # joint4 sits this far along the forearm
TOOL_LENGTH = 0.15  # wrist-pitch axis -> grasp point
GRIPPER_OPEN = 0.04
GRIPPER_CLOSED = 0.0

ACTION_DIM = 7
ARM_DOF = 6
# Position gains (N m / rad, N / m). DISCOVERSE uses 1000/1000/1000/350/350/100
# on heavier links; ours are lighter, so the gains scale down with them.
ARM_KP = (300.0, 300.0, 300.0, 80.0, 80.0, 40.0)
GRIPPER_KP = 100.0
JOINT_RANGES = np.array([
    (-3.1, 3.1), (-2.0, 2.0), (-0.3, 3.0), (-3.1, 3.1), (-2.6, 2.6), (-3.1, 3.1),
    (0.0, GRIPPER_OPEN),
])
# Arm folded above the base, gripper open: where every episode starts.
HOME_QPOS = np.array([0.0, -0.2, 2.2, 0.0, 1.1, 0.0, GRIPPER_OPEN])

TOOL_DOWN = jnp.pi  # tool direction angle from +z in the arm plane: pointing down
TOOL_FORWARD = jnp.pi / 2  # pointing horizontally away from the base


def _look_at(eye, target):
  eye, target = np.asarray(eye, float), np.asarray(target, float)
  fwd = target - eye
  fwd /= np.linalg.norm(fwd)
  right = np.cross(fwd, [0.0, 0.0, 1.0])
  right /= np.linalg.norm(right)
  up = np.cross(right, fwd)
  return " ".join(f"{v:.4f}" for v in (*right, *up))


SIDE_CAMERA_EYE = (0.78, -0.42, 0.42)
SIDE_CAMERA_TARGET = (0.30, 0.02, 0.03)


def arm_mjcf() -> str:
  """The robot's <body> tree (world-level), actuators and camera, as MJCF fragments."""
  kp = ARM_KP
  arm_geom = 'contype="0" conaffinity="0" rgba="0.82 0.82 0.85 1"'
  dark = 'contype="0" conaffinity="0" rgba="0.15 0.15 0.17 1"'
  finger = 'type="box" size="0.008 0.006 0.03" friction="2.0 0.01 0.001" condim="4" rgba="0.2 0.2 0.22 1"'
  r = JOINT_RANGES
  body = f"""
    <body name="base" pos="0 0 0">
      <geom type="box" size="0.07 0.07 0.03" pos="0 0 0.03" {dark}/>
      <body name="link1" pos="0 0 0.06" gravcomp="1">
        <inertial pos="0 0 0.03" mass="0.6" diaginertia="0.002 0.002 0.002"/>
        <joint name="joint1" axis="0 0 1" range="{r[0][0]} {r[0][1]}" damping="20" armature="0.05"/>
        <geom type="capsule" fromto="0 0 0 0 0 {SHOULDER_HEIGHT - 0.06}" size="0.04" {arm_geom}/>
        <body name="link2" pos="0 0 {SHOULDER_HEIGHT - 0.06}" gravcomp="1">
          <inertial pos="0 0 {UPPER_ARM / 2}" mass="0.8" diaginertia="0.006 0.006 0.0008"/>
          <joint name="joint2" axis="0 1 0" range="{r[1][0]} {r[1][1]}" damping="20" armature="0.05"/>
          <geom type="capsule" fromto="0 0 0 0 0 {UPPER_ARM}" size="0.032" {arm_geom}/>
          <body name="link3" pos="0 0 {UPPER_ARM}" gravcomp="1">
            <inertial pos="0 0 0.03" mass="0.3" diaginertia="0.0005 0.0005 0.0002"/>
            <joint name="joint3" axis="0 1 0" range="{r[2][0]} {r[2][1]}" damping="15" armature="0.05"/>
            <geom type="capsule" fromto="0 0 0 0 0 {FOREARM_ROLL_OFFSET}" size="0.03" {dark}/>
            <body name="link4" pos="0 0 {FOREARM_ROLL_OFFSET}" gravcomp="1">
              <inertial pos="0 0 0.1" mass="0.5" diaginertia="0.003 0.003 0.0004"/>
              <joint name="joint4" axis="0 0 1" range="{r[3][0]} {r[3][1]}" damping="5" armature="0.02"/>
              <geom type="capsule" fromto="0 0 0 0 0 {FOREARM - FOREARM_ROLL_OFFSET}" size="0.026" {arm_geom}/>
              <body name="link5" pos="0 0 {FOREARM - FOREARM_ROLL_OFFSET}" gravcomp="1">
                <inertial pos="0 0 0.02" mass="0.2" diaginertia="0.0002 0.0002 0.0001"/>
                <joint name="joint5" axis="0 1 0" range="{r[4][0]} {r[4][1]}" damping="5" armature="0.02"/>
                <geom type="capsule" fromto="0 -0.025 0 0 0.025 0" size="0.024" {dark}/>
                <body name="link6" pos="0 0 0.03" gravcomp="1">
                  <inertial pos="0 0 0.04" mass="0.25" diaginertia="0.0003 0.0003 0.0002"/>
                  <joint name="joint6" axis="0 0 1" range="{r[5][0]} {r[5][1]}" damping="2" armature="0.01"/>
                  <geom type="box" size="0.02 0.055 0.025" pos="0 0 {0.095 - 0.03 - 0.025}" {arm_geom}/>
                  <camera name="wrist" pos="0.05 0 0.07" xyaxes="0 1 0 1 0 0" fovy="72.5"/>
                  <site name="grasp" pos="0 0 {TOOL_LENGTH - 0.03}" size="0.005" rgba="1 0 0 0" group="4"/>
                  <body name="finger_left" pos="0 0 {0.10 - 0.03}" gravcomp="1">
                    <inertial pos="0 0.006 0.03" mass="0.04" diaginertia="1e-5 1e-5 1e-5"/>
                    <joint name="finger_left" type="slide" axis="0 1 0" range="0 {GRIPPER_OPEN}" damping="4" armature="0.01"/>
                    <geom name="finger_left" pos="0 0.006 0.03" {finger}/>
                  </body>
                  <body name="finger_right" pos="0 0 {0.10 - 0.03}" gravcomp="1">
                    <inertial pos="0 -0.006 0.03" mass="0.04" diaginertia="1e-5 1e-5 1e-5"/>
                    <joint name="finger_right" type="slide" axis="0 -1 0" range="0 {GRIPPER_OPEN}" damping="4" armature="0.01"/>
                    <geom name="finger_right" pos="0 -0.006 0.03" {finger}/>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
    <camera name="side" pos="{' '.join(map(str, SIDE_CAMERA_EYE))}" xyaxes="{_look_at(SIDE_CAMERA_EYE, SIDE_CAMERA_TARGET)}" fovy="72"/>
  """
  names = ["joint1", "joint2", "joint3", "joint4", "joint5", "joint6"]
  act = "\n".join(
      f'<position name="{n}" joint="{n}" kp="{k}" kv="0" ctrlrange="{lo} {hi}"/>'
      for n, k, (lo, hi) in zip(names, kp, JOINT_RANGES[:6])
  )
  act += (
      f'\n<position name="finger_left" joint="finger_left" kp="{GRIPPER_KP}" ctrlrange="0 {GRIPPER_OPEN}" forcerange="-15 15"/>'
      f'\n<position name="finger_right" joint="finger_right" kp="{GRIPPER_KP}" ctrlrange="0 {GRIPPER_OPEN}" forcerange="-15 15"/>'
  )
  return body, act


def action_to_ctrl(action: jnp.ndarray) -> jnp.ndarray:
  """7-D action -> 8 actuator controls (both fingers follow the 7th value)."""
  return jnp.concatenate([action[..., :7], action[..., 6:7]], axis=-1)


def grasp_joint_targets(pos, yaw, pitch=TOOL_DOWN, opening=GRIPPER_OPEN):
  """Closed-form IK: joint targets that put the grasp point at `pos`.

  pitch: direction of the tool in the arm's vertical plane, measured from +z
    (pi = pointing down, pi/2 = pointing horizontally outwards).
  yaw: world yaw of the fingers' closing axis (for a downward tool); for a
    forward tool the closing axis stays horizontal whatever `yaw` says.
  Unreachable targets are clipped to the nearest reachable wrist distance.
  """
  pos = jnp.asarray(pos, jnp.float32)
  j1 = jnp.arctan2(pos[1], pos[0])
  radial = jnp.hypot(pos[0], pos[1])
  wrist_r = radial - TOOL_LENGTH * jnp.sin(pitch)
  wrist_z = pos[2] - TOOL_LENGTH * jnp.cos(pitch)
  dr, dz = wrist_r, wrist_z - SHOULDER_HEIGHT
  dist = jnp.clip(jnp.hypot(dr, dz), abs(UPPER_ARM - FOREARM) + 1e-3, UPPER_ARM + FOREARM - 1e-3)
  cos_elbow = (dist**2 - UPPER_ARM**2 - FOREARM**2) / (2 * UPPER_ARM * FOREARM)
  j3 = jnp.arccos(jnp.clip(cos_elbow, -1.0, 1.0))
  j2 = jnp.arctan2(dr, dz) - jnp.arctan2(FOREARM * jnp.sin(j3), UPPER_ARM + FOREARM * jnp.cos(j3))
  j5 = pitch - j2 - j3
  # With the tool pointing down, the closing axis at joint6 = 0 is the arm
  # plane's normal (yaw j1 + pi/2); joint6 turns it by -joint6 about world z.
  j6 = (j1 + jnp.pi / 2) - yaw
  j6 = jnp.where(pitch > 2.0, j6, 0.0)
  j6 = (j6 + jnp.pi / 2) % jnp.pi - jnp.pi / 2  # the gripper is symmetric under a half turn
  return jnp.stack([j1, j2, j3, jnp.zeros_like(j1), j5, j6, jnp.asarray(opening, jnp.float32)])

"""MJCF assembly: the table, the robot and a task's objects in one model.

Concave things (bowl, cup, cabinet) are compounds of boxes so that both MJX
implementations collide them (the JAX one has no cylinder-box pair).
"""

from __future__ import annotations

import math

import mujoco

from envs import robot

PHYSICS_TIMESTEP = 0.005
CONTROL_DT = 0.05  # 20 Hz, the rate DISCOVERSE records demonstrations at

_OBJ = 'friction="1.2 0.01 0.001" condim="3"'


def _fmt(v):
  return " ".join(f"{x:.5g}" for x in v)


def box(size, pos=(0, 0, 0), rgba=(0.8, 0.2, 0.2, 1), euler=None, extra=""):
  e = f' euler="{_fmt(euler)}"' if euler is not None else ""
  return f'<geom type="box" size="{_fmt(size)}" pos="{_fmt(pos)}"{e} rgba="{_fmt(rgba)}" {_OBJ} {extra}/>'


def free_body(name, pos, geoms, mass=None):
  """A body with a free joint; `mass` sets one explicit inertial (else geom density)."""
  inertial = ""
  if mass is not None:
    i = mass * 0.04**2 / 6  # a ~4 cm object's inertia: only the mass matters for these tasks
    inertial = f'<inertial pos="0 0 0" mass="{mass}" diaginertia="{i:.3g} {i:.3g} {i:.3g}"/>'
  return f'<body name="{name}" pos="{_fmt(pos)}"><freejoint name="{name}"/>{inertial}{"".join(geoms)}</body>'


def ring(radius, height, thickness, n, rgba, z0=0.0, bottom=True, bottom_size=None):
  """Walls of a round open container as n boxes on a circle, plus a floor."""
  side = 2 * radius * math.tan(math.pi / n) + thickness
  geoms = []
  for i in range(n):
    a = 2 * math.pi * i / n
    # Walls float 1 mm above the floor's underside: only the floor touches the table.
    geoms.append(box((thickness / 2, side / 2, height / 2 - 0.0005),
                     (radius * math.cos(a), radius * math.sin(a), z0 + height / 2 + 0.0005),
                     rgba, euler=(0, 0, a)))
  if bottom:
    b = bottom_size or radius
    geoms.append(box((b, b, thickness / 2), (0, 0, z0 + thickness / 2), rgba))
  return geoms


def model_xml(name: str, objects: str, sensors: str = "") -> str:
  """The task's MJCF. impratio is MuJoCo's default (1): with 10, MJX-Warp held
  every grasp, but MuJoCo's C engine squeezed the jujube out of the fingers
  in every episode; at 1 both engines' experts succeed."""
  arm, actuators = robot.arm_mjcf()
  return f"""
<mujoco model="{name}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{PHYSICS_TIMESTEP}" iterations="8" ls_iterations="12" integrator="implicitfast" cone="elliptic" impratio="1">
    <flag warmstart="enable"/>
  </option>
  <visual><global offwidth="640" offheight="480"/><headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5"/></visual>
  <worldbody>
    <light pos="0.3 -0.3 1.5" dir="0 0.2 -1" diffuse="0.6 0.6 0.6" castshadow="false"/>
    <geom name="table" type="plane" size="0.9 0.7 0.01" pos="0.3 0 0" rgba="0.72 0.58 0.42 1" friction="1 0.01 0.001"/>
    {arm}
    {objects}
  </worldbody>
  <contact>
    <exclude body1="finger_left" body2="finger_right"/>
  </contact>
  <actuator>
    {actuators}
  </actuator>
  <sensor>
    {sensors}
  </sensor>
</mujoco>
"""


def compile_model(xml: str) -> mujoco.MjModel:
  return mujoco.MjModel.from_xml_string(xml)


# ---- object geometry shared by several tasks ------------------------------------

BOWL_RADIUS, BOWL_HEIGHT, BOWL_FLOOR = 0.05, 0.03, 0.006
CUP_RADIUS, CUP_HEIGHT, CUP_FLOOR = 0.028, 0.07, 0.005
PLATE_HALF, PLATE_THICK = 0.055, 0.006
BLOCK_HALF = 0.015
# A container's origin is the underside of its floor: what rests inside it
# rests at FLOOR + its own half height above that origin.


def bowl(name, pos, rgba):
  walls = ring(BOWL_RADIUS, BOWL_HEIGHT, BOWL_FLOOR, 8, rgba, bottom_size=BOWL_RADIUS * 0.8)
  return free_body(name, pos, walls, mass=0.15)


def cup(name, pos, rgba):
  walls = ring(CUP_RADIUS, CUP_HEIGHT, CUP_FLOOR, 8, rgba, bottom_size=CUP_RADIUS * 0.8)
  return free_body(name, pos, walls, mass=0.08)


def plate(name, pos, rgba=(0.93, 0.93, 0.9, 1)):
  return free_body(name, pos, [box((PLATE_HALF, PLATE_HALF, PLATE_THICK / 2), (0, 0, PLATE_THICK / 2), rgba)], mass=0.1)


def block(name, pos, rgba, half=(BLOCK_HALF, BLOCK_HALF, BLOCK_HALF), mass=0.03):
  return free_body(name, pos, [box(half, (0, 0, 0), rgba)], mass=mass)

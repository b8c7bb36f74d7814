"""Laptop close (L.C.): press the open lid shut.

The lid's hinge angle is 0 when closed. DISCOVERSE samples the lid joint in
U(0, pi/4); we read that as how far the lid leans towards the robot from
upright, i.e. an opening angle pi/2 - U(0, pi/4). Hinge friction holds it:
with MuJoCo's default soft friction constraint the lid crept (0.8 rad in 15 s
at the median) and shut itself in 39-46% of episodes with the robot at rest,
so the friction is made nearly hard (`solimpfriction` 0.999): the lid now
moves under 0.01 rad in 15 s untouched.
Success is DISCOVERSE's check as is (hinge angle under 0.1 rad): a closed
lid is the completed state (held 0.5 s like every success).
"""

import jax
import jax.numpy as jnp

from envs import expert, robot, scene
from envs.env import Phase, TabletopEnv
from envs.geometry import uniform_offset

BASE = (0.07, 0.09, 0.008)  # half sizes; the hinge runs along y at the far edge
LID = (0.065, 0.085, 0.003)


class LaptopClose(TabletopEnv):
  name = "laptop_close"
  abbr = "L.C."
  time_limit_s = 15.0
  objects = ("laptop",)
  extra_joints = ("lid",)

  def objects_xml(self):
    grey, screen = (0.35, 0.35, 0.4, 1), (0.1, 0.12, 0.2, 1)
    return f"""
      <body name="laptop" pos="0.33 0 {BASE[2]}">
        <freejoint name="laptop"/>
        <inertial pos="0 0 0" mass="1.5" diaginertia="0.005 0.005 0.005"/>
        {scene.box(BASE, (0, 0, 0), grey)}
        <body name="lid" pos="{BASE[0]} 0 {BASE[2]}">
          <joint name="lid" type="hinge" axis="0 1 0" range="0 2.0" damping="0.05" frictionloss="0.12" solimpfriction="0.999 0.9999 0.001"/>
          <inertial pos="{-LID[0]} 0 {LID[2]}" mass="0.1" diaginertia="0.0003 0.0003 0.0003"/>
          {scene.box(LID, (-LID[0], 0, LID[2]), grey)}
          {scene.box((LID[0] - 0.008, LID[1] - 0.008, 0.0005), (-LID[0], 0, -0.0005), screen, extra='contype="0" conaffinity="0"')}
        </body>
      </body>"""

  def sample_objects(self, key, qpos):
    k1, k2 = jax.random.split(key)
    xy = self.nominal("laptop")[:2] + uniform_offset(k1, (0.1, 0.1))
    qpos = self.place(qpos, "laptop", jnp.append(xy, BASE[2]))
    angle = jnp.pi / 2 - jax.random.uniform(k2, (), minval=0.0, maxval=jnp.pi / 4)
    return qpos.at[self._qadr["lid"]].set(angle)

  def success(self, data):
    return jnp.abs(self.qpos_of(data, "lid")) < 0.1

  def expert_plan(self):
    radius = 0.75 * 2 * LID[0]  # press here along the lid, from the hinge

    def on_lid(env, d, angle, clearance):
      hinge = env.pos(d, "lid")
      heading = jnp.array([-jnp.cos(angle), 0.0, jnp.sin(angle)])  # hinge -> lid tip
      normal = jnp.array([jnp.sin(angle), 0.0, jnp.cos(angle)])  # out of the lid's back
      # Fingertips (1 cm below the grasp point) rest `clearance` off the lid's back.
      p = hinge + radius * heading + (2 * LID[2] + clearance) * normal + jnp.array([0.0, 0.0, 0.01])
      return expert.top(p, None, robot.GRIPPER_CLOSED)

    def sweep(frac, clearance):
      return Phase(lambda env, d: on_lid(env, d, frac * (env.qpos_of(d, "lid") + 0.35), clearance), tol=0.02)

    def above(env, d):
      hinge = env.pos(d, "lid")
      return expert.top(hinge + jnp.array([0.02, 0.0, 0.2]), None, robot.GRIPPER_CLOSED)

    return [Phase(above, tol=0.05), sweep(1.0, 0.02), sweep(0.7, 0.0), sweep(0.45, -0.01),
            sweep(0.2, -0.015), sweep(0.0, -0.015)]

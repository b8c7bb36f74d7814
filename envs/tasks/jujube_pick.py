"""Jujube pick (J.P.): grasp a jujube lying on the table and lift it.

DISCOVERSE checks that the jujube is within 3 cm of the gripper's grasp point
once, after its expert has lifted it. Checked at every step, that distance
alone passes the open gripper around a jujube still on the table, so ours
also asks for the lift: the jujube at least 3 cm above its resting height.
"""

import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv
from envs.geometry import uniform_offset

RADIUS = 0.013
REST_Z = RADIUS - 0.001  # centre height of a jujube lying on the table
LIFT = 0.03


def jujube_xml(xy):
  geom = (f'<geom type="ellipsoid" size="{RADIUS} {RADIUS} {RADIUS - 0.001}" '
          f'rgba="0.55 0.12 0.08 1" {scene._OBJ}/>')
  return scene.free_body("jujube", (*xy, REST_Z), [geom], mass=0.02)


class JujubePick(TabletopEnv):
  name = "jujube_pick"
  abbr = "J.P."
  time_limit_s = 10.0
  objects = ("jujube",)

  def objects_xml(self):
    return jujube_xml((0.32, 0.0))

  def sample_objects(self, key, qpos):
    xy = self.nominal("jujube")[:2] + uniform_offset(key, (0.10, 0.05))
    return self.place(qpos, "jujube", jnp.append(xy, REST_Z))

  def success(self, data):
    p = self.pos(data, "jujube")
    return (p[2] > REST_Z + LIFT) & (jnp.linalg.norm(p - self.grasp_pos(data)) < 0.03)

  def expert_plan(self):
    # Pick, then lift: the same motion as a pick-and-place that ends above the start.
    lift = lambda env, d: env.pos(d, "jujube") + jnp.array([0.0, 0.0, 0.05])
    return expert.pick_and_place("jujube", lift)[:5]

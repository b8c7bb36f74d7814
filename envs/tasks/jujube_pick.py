"""Jujube pick (J.P.): grasp a jujube lying on the table."""

import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv, uniform_offset

RADIUS = 0.013


def jujube_xml(xy):
  geom = (f'<geom type="ellipsoid" size="{RADIUS} {RADIUS} {RADIUS - 0.001}" '
          f'rgba="0.55 0.12 0.08 1" {scene._OBJ}/>')
  return scene.free_body("jujube", (*xy, RADIUS - 0.001), [geom], mass=0.02)


class JujubePick(TabletopEnv):
  name = "jujube_pick"
  abbr = "J.P."
  time_limit_s = 10.0
  objects = ("jujube",)

  def objects_xml(self):
    return jujube_xml((0.32, 0.0))

  def sample_objects(self, key, qpos):
    xy = self.nominal("jujube")[:2] + uniform_offset(key, (0.10, 0.05))
    return self.place(qpos, "jujube", jnp.append(xy, RADIUS - 0.001))

  def success(self, data):
    # DISCOVERSE: the jujube within 3 cm of the gripper's grasp point.
    return jnp.linalg.norm(self.pos(data, "jujube") - self.grasp_pos(data)) < 0.03

  def expert_plan(self):
    # Pick, then lift: the same motion as a pick-and-place that ends above the start.
    lift = lambda env, d: env.pos(d, "jujube") + jnp.array([0.0, 0.0, 0.05])
    return expert.pick_and_place("jujube", lift)[:5]

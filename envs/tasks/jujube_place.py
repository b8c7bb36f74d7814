"""Jujube place (J.Pl., few-shot): drop the jujube into the coffee cup.

Extends DISCOVERSE's check (cup upright, jujube within 2 cm of it in xy, read
once after its expert has released and retreated) with what an every-step
check needs: the jujube lies on the cup's floor and the gripper no longer
touches it.
"""

import jax
import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv
from envs.geometry import rests_on, uniform_offset, upright, xy_dist
from envs.tasks.jujube_pick import RADIUS, REST_Z, jujube_xml


class JujubePlace(TabletopEnv):
  name = "jujube_place"
  abbr = "J.Pl."
  time_limit_s = 15.0
  objects = ("jujube", "cup")

  def objects_xml(self):
    return jujube_xml((0.29, -0.12)) + scene.cup("cup", (0.32, 0.10, 0.0), (0.9, 0.9, 0.92, 1))

  def sample_objects(self, key, qpos):
    k1, k2 = jax.random.split(key)
    jujube = self.nominal("jujube")[:2] + uniform_offset(k1, (0.10, 0.05))
    cup = self.nominal("cup")[:2] + uniform_offset(k2, (0.10, 0.05))
    qpos = self.place(qpos, "jujube", jnp.append(jujube, REST_Z))
    return self.place(qpos, "cup", jnp.append(cup, 0.0))

  def success(self, data):
    jujube, cup = self.pos(data, "jujube"), self.pos(data, "cup")
    return (upright(self.mat(data, "cup")) & (xy_dist(jujube, cup) < 0.02)
            & rests_on(jujube, cup, scene.CUP_FLOOR + REST_Z) & self.released(data, "jujube"))

  def expert_plan(self):
    above_cup = lambda env, d: env.pos(d, "cup") + jnp.array([0.0, 0.0, scene.CUP_HEIGHT + RADIUS + 0.012])
    return expert.pick_and_place("jujube", above_cup, opening=0.03)

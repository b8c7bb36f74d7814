"""Kiwi place (K.P.): put the kiwi into the bowl and let go.

Extends DISCOVERSE's check (bowl upright, kiwi within 2 cm of the bowl in
xy, read once after its expert has released and retreated): checked every
step, xy alone passes a kiwi carried above the bowl, so ours also asks that
the kiwi rests on the bowl's floor and that the gripper no longer touches it.
"""

import jax
import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv
from envs.geometry import rests_on, uniform_offset, upright, xy_dist

KIWI = (0.026, 0.022, 0.021)


class KiwiPlace(TabletopEnv):
  name = "kiwi_place"
  abbr = "K.P."
  time_limit_s = 15.0
  objects = ("kiwi", "bowl")

  def objects_xml(self):
    kiwi = f'<geom type="ellipsoid" size="{scene._fmt(KIWI)}" rgba="0.45 0.35 0.15 1" {scene._OBJ}/>'
    return (scene.free_body("kiwi", (0.30, -0.10, KIWI[2]), [kiwi], mass=0.06)
            + scene.bowl("bowl", (0.32, 0.10, 0.0), (0.85, 0.85, 0.8, 1)))

  def sample_objects(self, key, qpos):
    k1, k2 = jax.random.split(key)
    kiwi = self.nominal("kiwi")[:2] + uniform_offset(k1, (0.08, 0.03))
    bowl = self.nominal("bowl")[:2] + uniform_offset(k2, (0.05, 0.03))
    qpos = self.place(qpos, "kiwi", jnp.append(kiwi, KIWI[2]))
    return self.place(qpos, "bowl", jnp.append(bowl, 0.0))

  def success(self, data):
    kiwi, bowl = self.pos(data, "kiwi"), self.pos(data, "bowl")
    return (upright(self.mat(data, "bowl")) & (xy_dist(kiwi, bowl) < 0.02)
            & rests_on(kiwi, bowl, scene.BOWL_FLOOR + KIWI[2]) & self.released(data, "kiwi"))

  def expert_plan(self):
    above_bowl = lambda env, d: env.pos(d, "bowl") + jnp.array([0.0, 0.0, scene.BOWL_HEIGHT + KIWI[2] + 0.01])
    return expert.pick_and_place("kiwi", above_bowl)

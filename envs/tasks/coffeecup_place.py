"""Coffeecup place (C.P.): put the cup, upright, onto the plate and let go.

Extends DISCOVERSE's check (cup upright, within 2 cm of the plate in xy, read
once after its expert has released and retreated) with what an every-step
check needs: the cup stands on the plate and the gripper no longer touches it.

DISCOVERSE moves the cup +-0.20 m along its table's x; our arm is shorter, so
that wide range runs across the table (our y) and the narrow one along x.
"""

import jax
import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv
from envs.geometry import rests_on, uniform_offset, upright, xy_dist

CUP_GRASP = scene.CUP_HEIGHT - 0.02  # grasp height on the cup's wall


class CoffeecupPlace(TabletopEnv):
  name = "coffeecup_place"
  abbr = "C.P."
  time_limit_s = 15.0
  objects = ("cup", "plate")

  def objects_xml(self):
    return (scene.cup("cup", (0.30, -0.02, 0.0), (0.95, 0.95, 0.97, 1))
            + scene.plate("plate", (0.34, 0.22, 0.0)))

  def sample_objects(self, key, qpos):
    k1, k2 = jax.random.split(key)
    cup = self.nominal("cup")[:2] + uniform_offset(k1, (0.06, 0.12))
    plate = self.nominal("plate")[:2] + uniform_offset(k2, (0.0625, 0.02))
    qpos = self.place(qpos, "cup", jnp.append(cup, 0.0))
    return self.place(qpos, "plate", jnp.append(plate, 0.0))

  def success(self, data):
    return cup_on_plate(self, data) & self.released(data, "cup")

  def expert_plan(self):
    on_plate = lambda env, d: env.pos(d, "plate") + jnp.array([0.0, 0.0, scene.PLATE_THICK + 0.003])
    return expert.pick_and_place("cup", on_plate, grasp_dz=CUP_GRASP, hover=0.06)


def cup_on_plate(env, data):
  """The cup upright, centred on the plate (2 cm, xy) and standing on it."""
  cup, plate = env.pos(data, "cup"), env.pos(data, "plate")
  return upright(env.mat(data, "cup")) & (xy_dist(cup, plate) < 0.02) & rests_on(cup, plate, scene.PLATE_THICK)

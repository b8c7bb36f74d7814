"""Cuplid cover (C.C., few-shot): cup onto the plate, then the lid onto the cup.

Extends DISCOVERSE's check (cup upright on the plate, lid on the cup, both
within 2 cm in xy, read once after its expert has released and retreated)
with what an every-step check needs: the cup stands on the plate, the lid
sits on the cup's rim, and the gripper touches neither.

The lid starts on a wooden block. DISCOVERSE shifts the cup by 0.05-0.10 m
along x; we read that as a one-sided offset U(0.05, 0.10).
"""

import jax
import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv
from envs.geometry import rests_on, uniform_offset, xy_dist
from envs.tasks.coffeecup_place import CUP_GRASP, cup_on_plate

LID_HALF, LID_THICK = 0.036, 0.006
KNOB = (0.008, 0.008, 0.012)
STAND = (0.03, 0.03, 0.02)  # wooden block under the lid


class CuplidCover(TabletopEnv):
  name = "cuplid_cover"
  abbr = "C.C."
  time_limit_s = 20.0
  objects = ("cup", "plate", "lid")

  def objects_xml(self):
    lid = [scene.box((LID_HALF, LID_HALF, LID_THICK / 2), (0, 0, LID_THICK / 2), (0.3, 0.3, 0.35, 1)),
           scene.box(KNOB, (0, 0, LID_THICK + KNOB[2]), (0.2, 0.2, 0.25, 1))]
    stand = [scene.box(STAND, (0, 0, STAND[2]), (0.6, 0.45, 0.3, 1))]
    return (scene.cup("cup", (0.22, -0.14, 0.0), (0.95, 0.95, 0.97, 1))
            + scene.plate("plate", (0.34, 0.0, 0.0))
            + scene.free_body("stand", (0.26, 0.16, 0.0), stand, mass=0.5)
            + scene.free_body("lid", (0.26, 0.16, 2 * STAND[2]), lid, mass=0.04))

  def sample_objects(self, key, qpos):
    k1, k2, k3, k4 = jax.random.split(key, 4)
    cup = self.nominal("cup")[:2] + jnp.array([jax.random.uniform(k1, (), minval=0.05, maxval=0.10),
                                                jax.random.uniform(k4, (), minval=-0.03, maxval=0.03)])
    plate = self.nominal("plate")[:2] + uniform_offset(k2, (0.05, 0.02))
    lid = self.nominal("lid")[:2] + uniform_offset(k3, (0.05, 0.05))
    qpos = self.place(qpos, "cup", jnp.append(cup, 0.0))
    qpos = self.place(qpos, "plate", jnp.append(plate, 0.0))
    qpos = self.place(qpos, "stand", jnp.append(lid, 0.0))
    return self.place(qpos, "lid", jnp.append(lid, 2 * STAND[2]))

  def success(self, data):
    cup, lid = self.pos(data, "cup"), self.pos(data, "lid")
    return (cup_on_plate(self, data) & (xy_dist(lid, cup) < 0.02) & rests_on(lid, cup, scene.CUP_HEIGHT)
            & self.released(data, "cup", "lid"))

  def expert_plan(self):
    on_plate = lambda env, d: env.pos(d, "plate") + jnp.array([0.0, 0.0, scene.PLATE_THICK + 0.003])
    on_cup = lambda env, d: env.pos(d, "cup") + jnp.array([0.0, 0.0, scene.CUP_HEIGHT + 0.004])
    cup = expert.pick_and_place("cup", on_plate, grasp_dz=CUP_GRASP, hover=0.06)
    lid = expert.pick_and_place("lid", on_cup, grasp_dz=LID_THICK + KNOB[2], hover=0.06,
                                opening=0.025, grasp_yaw=expert.face_yaw("lid"))
    return cup + lid

"""Block place (B.P., few-shot): put the green block into the pink bowl and let go.

Extends DISCOVERSE's check (bowl upright, block within 2 cm of it in xy, read
once after its expert has released and retreated) with what an every-step
check needs: the block rests on the bowl's floor and the gripper no longer
touches it.
"""

import jax
import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv
from envs.geometry import rests_on, uniform_offset, upright, xy_dist

H = scene.BLOCK_HALF


class BlockPlace(TabletopEnv):
  name = "block_place"
  abbr = "B.P."
  time_limit_s = 10.0
  objects = ("block", "bowl")

  def objects_xml(self):
    return (scene.block("block", (0.27, -0.13, H), (0.2, 0.7, 0.25, 1))
            + scene.bowl("bowl", (0.33, 0.11, 0.0), (0.95, 0.55, 0.7, 1)))

  def sample_objects(self, key, qpos):
    k1, k2 = jax.random.split(key)
    block = self.nominal("block")[:2] + uniform_offset(k1, (0.12, 0.08))
    bowl = self.nominal("bowl")[:2] + uniform_offset(k2, (0.10, 0.05))
    qpos = self.place(qpos, "block", jnp.append(block, H))
    return self.place(qpos, "bowl", jnp.append(bowl, 0.0))

  def success(self, data):
    block, bowl = self.pos(data, "block"), self.pos(data, "bowl")
    return (upright(self.mat(data, "bowl")) & (xy_dist(block, bowl) < 0.02)
            & rests_on(block, bowl, scene.BOWL_FLOOR + H) & self.released(data, "block"))

  def expert_plan(self):
    above_bowl = lambda env, d: env.pos(d, "bowl") + jnp.array([0.0, 0.0, scene.BOWL_HEIGHT + H + 0.01])
    return expert.pick_and_place("block", above_bowl, grasp_yaw=expert.face_yaw("block"), opening=0.028)

"""Block bridge place (B.B.P.): build a bridge from two pieces and lay two blocks across it.

DISCOVERSE's check mixes one piece's x with the other's y; we implement its
intent: the two bridge pieces parallel and side by side with their centres
3 cm +- 2 mm apart across their width and aligned along their length (within
1 cm), and both blocks lying flat on top of the bridge (long axis
horizontal, within 0.11 m of the bridge's centre, the DISCOVERSE tolerance).
DISCOVERSE reads it once, after its expert has released and retreated;
checked every step, it also needs each block resting on the pieces' tops
(not carried above them) and no object touched by the gripper. Every object
starts within +-1 mm of its nominal pose.
"""

import jax
import jax.numpy as jnp

from envs import expert, scene
from envs.env import TabletopEnv
from envs.geometry import rests_on, upright

PIECE = (0.01, 0.03, 0.015)  # half sizes: 2 cm wide (x), 6 cm long (y), 3 cm tall
BLOCK = (0.025, 0.01, 0.01)  # 5 cm long (x), lying flat
GAP = 0.03
BLOCKS = ("green", "purple")


class BlockBridgePlace(TabletopEnv):
  name = "block_bridge_place"
  abbr = "B.B.P."
  time_limit_s = 70.0
  objects = ("bridge1", "bridge2") + BLOCKS

  def objects_xml(self):
    wood = (0.75, 0.6, 0.4, 1)
    return (scene.block("bridge1", (0.30, 0.0, PIECE[2]), wood, PIECE, mass=0.05)
            + scene.block("bridge2", (0.30, 0.17, PIECE[2]), wood, PIECE, mass=0.05)
            + scene.block("green", (0.24, -0.14, BLOCK[2]), (0.2, 0.7, 0.25, 1), BLOCK, mass=0.03)
            + scene.block("purple", (0.34, -0.14, BLOCK[2]), (0.55, 0.25, 0.7, 1), BLOCK, mass=0.03))

  def sample_objects(self, key, qpos):
    keys = jax.random.split(key, len(self.objects))
    for k, b in zip(keys, self.objects):
      xyz = self.nominal(b) + jnp.append(jax.random.uniform(k, (2,), minval=-0.001, maxval=0.001), 0.0)
      qpos = self.place(qpos, b, xyz)
    return qpos

  def success(self, data):
    a, b = self.pos(data, "bridge1"), self.pos(data, "bridge2")
    across = self.mat(data, "bridge1")[:2, 0]  # piece 1's width direction
    along = self.mat(data, "bridge1")[:2, 1]
    d = (b - a)[:2]
    bridge = (jnp.abs(jnp.abs(d @ across) - GAP) <= 0.002) & (jnp.abs(d @ along) < 0.01)
    bridge &= upright(self.mat(data, "bridge1")) & upright(self.mat(data, "bridge2"))
    centre = (a + b) / 2
    for blk in BLOCKS:
      p, m = self.pos(data, blk), self.mat(data, blk)
      flat = (jnp.abs(m[2, 0]) < 0.1) & upright(m)
      on_top = rests_on(p, centre, PIECE[2] + BLOCK[2])
      bridge &= flat & on_top & (jnp.linalg.norm((p - centre)[:2]) < 0.11)
    return bridge & self.released(data, *self.objects)

  def expert_plan(self):
    # Fingers close along y: across a block's 2 cm width and along a piece's
    # 6 cm length, so that no finger enters the 1 cm gap between the pieces.
    along_y = expert.fixed_yaw(jnp.pi / 2)
    beside = lambda env, d: env.pos(d, "bridge1") + jnp.array([GAP, 0.0, 0.002])

    def across(offset):
      def target(env, d):
        centre = (env.pos(d, "bridge1") + env.pos(d, "bridge2")) / 2
        return centre.at[2].set(2 * PIECE[2] + BLOCK[2] + 0.003) + jnp.array([0.0, offset, 0.0])
      return target

    piece = expert.pick_and_place("bridge2", beside, grasp_yaw=along_y, place_yaw=along_y, hover=0.06)
    blk1 = expert.pick_and_place("green", across(-0.02), grasp_dz=0.004, grasp_yaw=along_y,
                                 place_yaw=along_y, opening=0.022, release_opening=0.014, hover=0.06)
    blk2 = expert.pick_and_place("purple", across(0.02), grasp_dz=0.004, grasp_yaw=along_y,
                                 place_yaw=along_y, opening=0.022, release_opening=0.014, hover=0.06)
    return piece + blk1 + blk2

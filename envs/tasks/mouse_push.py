"""Mouse push (M.P., few-shot): push the mouse onto the mouse pad with the closed gripper.

Success is DISCOVERSE's check as is (mouse within 4 cm of the pad's centre in
xy): a pushed mouse lies on the table, so the state is the completion (held
0.5 s like every success; the pusher may still touch it).
"""

import jax
import jax.numpy as jnp

from envs import expert, robot, scene
from envs.env import Phase, TabletopEnv
from envs.geometry import uniform_offset, xy_dist

MOUSE = (0.03, 0.02, 0.014)
PAD = (0.06, 0.05, 0.001)
FINGER = 0.008  # closed fingers' half depth along the push (closing axis across it)
PUSH_Z = 0.022  # grasp point height while pushing: fingertips 1.2 cm up, at the mouse's waist
BACKOFF = 0.015  # clearance behind the mouse before the descent
STEP = 0.035  # push length per closed-loop phase
N_PUSH = 9


class MousePush(TabletopEnv):
  name = "mouse_push"
  abbr = "M.P."
  time_limit_s = 15.0
  objects = ("mouse", "pad")

  def objects_xml(self):
    mouse = f'<geom type="ellipsoid" size="{scene._fmt(MOUSE)}" rgba="0.9 0.9 0.92 1" friction="0.4 0.01 0.001" condim="3"/>'
    pad = scene.box(PAD, (0, 0, PAD[2]), (0.15, 0.15, 0.18, 1))
    return (scene.free_body("mouse", (0.24, 0.0, MOUSE[2]), [mouse], mass=0.05)
            + scene.free_body("pad", (0.38, 0.0, 0.0), [pad], mass=0.5))

  def sample_objects(self, key, qpos):
    k1, k2 = jax.random.split(key)
    mouse = self.nominal("mouse")[:2] + uniform_offset(k1, (0.03, 0.02))
    pad = self.nominal("pad")[:2] + uniform_offset(k2, (0.05, 0.025))
    qpos = self.place(qpos, "mouse", jnp.append(mouse, MOUSE[2]))
    return self.place(qpos, "pad", jnp.append(pad, 0.0))

  def success(self, data):
    return xy_dist(self.pos(data, "mouse"), self.pos(data, "pad")) < 0.04

  def expert_plan(self):
    # Closed-loop pushing: every phase re-reads the mouse and pushes it a short
    # step along the mouse -> pad line from just behind its current outline, so
    # the mouse turning (a pushed ellipsoid swings its long side round to the
    # pusher) or sliding sideways is corrected at the next phase.
    return ([Phase(lambda env, d: _push(env, d, 0.0, 0.08, BACKOFF), tol=0.03),
             Phase(lambda env, d: _push(env, d, 0.0, PUSH_Z, BACKOFF), tol=0.01)]
            + [Phase(lambda env, d: _push(env, d, STEP, PUSH_Z), tol=0.012) for _ in range(N_PUSH)])


def _push(env, d, step, height, backoff=0.0):
  """Grasp-point goal `step` along the push from contact behind the mouse."""
  m, p = env.pos(d, "mouse"), env.pos(d, "pad")
  u = (p - m).at[2].set(0.0)
  dist = jnp.linalg.norm(u)
  u = u / (dist + 1e-6)
  ub = env.mat(d, "mouse").T @ u  # push direction in the mouse's frame
  reach = jnp.sqrt((MOUSE[0] * ub[0]) ** 2 + (MOUSE[1] * ub[1]) ** 2)  # ellipse's support radius
  # The mouse's centre should stop on the pad's centre: never step past it.
  adv = jnp.minimum(step, jnp.maximum(dist - 0.004, 0.0))
  q = m - u * (reach + FINGER + 0.002 + backoff) + u * adv
  yaw = jnp.arctan2(u[1], u[0]) + jnp.pi / 2  # closing axis across the push: the 2.4 cm face pushes
  goal = expert.top(q.at[2].set(height), yaw, robot.GRIPPER_CLOSED)
  # Once the mouse sits on the pad's centre the push direction is noise: hold still.
  hold = jnp.append(d.qpos[:robot.ARM_DOF], robot.GRIPPER_CLOSED)
  return jnp.where((step > 0) & (dist < 0.012), hold, goal)

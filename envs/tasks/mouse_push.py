"""Mouse push (M.P., few-shot): push the mouse onto the mouse pad with the closed gripper."""

import jax
import jax.numpy as jnp

from envs import expert, robot, scene
from envs.env import Phase, TabletopEnv, uniform_offset, xy_dist

MOUSE = (0.03, 0.02, 0.014)
PAD = (0.06, 0.05, 0.001)
FINGER = 0.012  # closed fingers' half depth along the push


class MousePush(TabletopEnv):
  name = "mouse_push"
  abbr = "M.P."
  time_limit_s = 15.0
  objects = ("mouse", "pad")

  def objects_xml(self):
    mouse = f'<geom type="ellipsoid" size="{scene._fmt(MOUSE)}" rgba="0.9 0.9 0.92 1" friction="0.4 0.01 0.001" condim="3"/>'
    pad = scene.box(PAD, (0, 0, PAD[2]), (0.15, 0.15, 0.18, 1))
    return (scene.free_body("mouse", (0.24, 0.0, MOUSE[2]), [mouse], mass=0.05)
            + scene.free_body("pad", (0.38, 0.0, 0.0), [pad], mass=0.2))

  def sample_objects(self, key, qpos):
    k1, k2 = jax.random.split(key)
    mouse = self.nominal("mouse")[:2] + uniform_offset(k1, (0.03, 0.02))
    pad = self.nominal("pad")[:2] + uniform_offset(k2, (0.05, 0.025))
    qpos = self.place(qpos, "mouse", jnp.append(mouse, MOUSE[2]))
    return self.place(qpos, "pad", jnp.append(pad, 0.0))

  def success(self, data):
    return xy_dist(self.pos(data, "mouse"), self.pos(data, "pad")) < 0.04

  def expert_plan(self):
    def push_point(env, d, frac, height, extra=0.0):
      m, p = env.pos(d, "mouse"), env.pos(d, "pad")
      u = (p - m).at[2].set(0.0)
      u = u / (jnp.linalg.norm(u) + 1e-6)
      start = m - u * (MOUSE[0] + FINGER + 0.015)
      end = p - u * (MOUSE[0] + FINGER) + u * extra
      q = start + frac * (end - start)
      return expert.top(q.at[2].set(height), None, robot.GRIPPER_CLOSED)

    # The start of the push is latched from the mouse pose; later waypoints use
    # the pad (static) and the pose read at each phase's start.
    return [Phase(lambda env, d: push_point(env, d, 0.0, 0.08), tol=0.02),
            Phase(lambda env, d: push_point(env, d, 0.0, 0.022), tol=0.01)] + [
            Phase(lambda env, d, f=f: _towards(env, d, f), tol=0.015) for f in (0.35, 0.65, 1.0)]


def _towards(env, d, frac):
  """Waypoint `frac` of the way from the gripper to the pushing end point."""
  g, p = env.grasp_pos(d), env.pos(d, "pad")
  m = env.pos(d, "mouse")
  u = (p - m).at[2].set(0.0)
  u = u / (jnp.linalg.norm(u) + 1e-6)
  end = p - u * (MOUSE[0] + FINGER - 0.005)
  q = g + jnp.clip(frac, 0, 1) * (end - g)
  return expert.top(q.at[2].set(0.022), None, robot.GRIPPER_CLOSED)

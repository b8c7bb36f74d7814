"""Drawer open (D.O.): pull the cabinet's drawer out by its handle (no randomisation).

DISCOVERSE's check (drawer slid out past a threshold) is already a completed
state: an opened drawer stays open, so it is used as is (held 0.5 s like every
success).
"""

import jax.numpy as jnp

from envs import expert, robot, scene
from envs.env import Phase, TabletopEnv

FRONT_X = 0.46  # drawer front face, closed
HANDLE_Z = 0.10
PULL = 0.18
# Grasp point 2.2 cm behind the handle centre (handle half depth 1 cm, closed
# fingers 0.8 cm half thick along x), fingertips 2 cm below the handle centre.
HOOK_DX = 0.022
HOOK_Z = HANDLE_Z - 0.01
_VIS = 'contype="0" conaffinity="0"'


class DrawerOpen(TabletopEnv):
  name = "drawer_open"
  abbr = "D.O."
  time_limit_s = 15.0
  objects = ()
  extra_joints = ("drawer",)

  def objects_xml(self):
    wood, dark = (0.55, 0.4, 0.28, 1), (0.25, 0.25, 0.28, 1)
    cx = FRONT_X + 0.11
    cabinet = "".join([
        scene.box((0.12, 0.16, 0.01), (cx, 0, 0.19), wood, extra=_VIS),
        scene.box((0.12, 0.01, 0.095), (cx, 0.15, 0.095), wood, extra=_VIS),
        scene.box((0.12, 0.01, 0.095), (cx, -0.15, 0.095), wood, extra=_VIS),
        scene.box((0.01, 0.16, 0.095), (cx + 0.11, 0, 0.095), wood, extra=_VIS),
    ])
    drawer = f"""
      <body name="drawer" pos="{FRONT_X} 0 0.1">
        <joint name="drawer" type="slide" axis="-1 0 0" range="0 0.2" damping="3"/>
        <inertial pos="0.1 0 0" mass="0.5" diaginertia="0.005 0.005 0.005"/>
        {scene.box((0.008, 0.14, 0.08), (0.008, 0, 0), (0.68, 0.52, 0.36, 1), extra=_VIS)}
        {scene.box((0.1, 0.13, 0.005), (0.1, 0, -0.07), wood, extra=_VIS)}
        {scene.box((0.015, 0.005, 0.005), (-0.015, 0, 0.03), dark, extra=_VIS)}
        {scene.box((0.015, 0.005, 0.005), (-0.015, 0, -0.03), dark, extra=_VIS)}
        <geom name="handle" type="box" size="0.01 0.01 0.035" pos="-0.035 0 {HANDLE_Z - 0.1}" rgba="{scene._fmt(dark)}" friction="1.5 0.01 0.001"/>
      </body>"""
    return f'<body name="cabinet" pos="0 0 0">{cabinet}</body>' + drawer

  def success(self, data):
    return self.qpos_of(data, "drawer") > 0.15

  def expert_plan(self):
    # Hook, not pinch: the closed fingers (tool down) drop into the gap between
    # the handle and the drawer front and pull the handle's back face towards
    # the robot. A pushing contact needs no grip force, so nothing can slip.
    # Only the handle collides (the drawer and cabinet are visual), so the
    # fingers cannot snag on the front panel.
    closed = robot.GRIPPER_CLOSED

    def behind_handle(env, d, dx, z):
      h = d.geom_xpos[env.mj_model.geom("handle").id]
      p = jnp.array([h[0] + HOOK_DX + dx, h[1], z])
      return expert.top(p, None, closed)

    return [
        Phase(lambda env, d: behind_handle(env, d, 0.0, HANDLE_Z + 0.12), tol=0.02),
        Phase(lambda env, d: behind_handle(env, d, 0.0, HOOK_Z), tol=0.01),
        Phase(lambda env, d: behind_handle(env, d, -PULL, HOOK_Z), tol=0.02),
    ]

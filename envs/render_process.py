"""Drawing a batch of states with MuJoCo's OpenGL renderer, on a thread or in a process of its own.

`Drawer` is the drawing itself, used by `envs.mujoco_batch.CameraRenderer`'s worker threads and,
with `processes=True`, by the processes `serve` runs in. Why processes: on a CPU, software
OpenGL (Mesa's llvmpipe) holds Python's GIL for part of each draw (on one VM two render threads
drew LIBERO's 128x128 images 1.6x as fast as one, not 2x); processes share no GIL. Measured
beside threads, they give -4% to +18% episodes/s (docs/libero.md, "Speed"). This module imports
MuJoCo and numpy only, so a render process starts without JAX.
"""

from __future__ import annotations

import copy
import os
import socket
import subprocess
import sys
import traceback
from multiprocessing.connection import Connection
from pathlib import Path

import mujoco
import numpy as np


def render_model(model: mujoco.MjModel, h: int, w: int, multisample: bool = False) -> mujoco.MjModel:
  """A copy of `model` whose offscreen buffer is the image size, without multisampling unless asked."""
  m = copy.copy(model)
  m.vis.global_.offwidth, m.vis.global_.offheight = w, h
  if not multisample:
    m.vis.quality.offsamples = 0
  return m


def set_look(model: mujoco.MjModel, look: dict, i) -> None:
  """Write row `i` of each field of `look` into the model (only rendering reads these fields)."""
  for f, v in look.items():
    getattr(model, f)[:] = v[i]


class Drawer:
  """One renderer on its own copy of the model (`render_model`'s): draws states by their qpos rows.

  An OpenGL context belongs to the thread that made it: make, use and close a Drawer on one thread."""

  def __init__(self, model: mujoco.MjModel, size, cameras, flags_off=(), hidden_groups=(), max_geom: int = 10000,
               look_fields=()):
    self.model, self.cameras = model, tuple(cameras)
    self.renderer = mujoco.Renderer(model, *size, max_geom=max_geom)
    try:
      for flag in flags_off:
        self.renderer.scene.flags[getattr(mujoco.mjtRndFlag, flag)] = 0
      self.option = mujoco.MjvOption()
      for group in hidden_groups:
        self.option.geomgroup[group] = 0
      self.data = mujoco.MjData(model)
      self.cam_ids = [model.camera(c).id for c in self.cameras]
      self.own = {f: getattr(model, f)[None].copy() for f in look_fields}  # the model's look, as row 0
    except Exception:
      self.renderer.close()
      raise
    self.shifted = False  # the model holds another look than its own

  def draw(self, qpos: np.ndarray, ids, out: dict, looks: dict | None = None) -> None:
    """Draw states `ids` (rows of `qpos`) into out[camera][i]; `looks` ({field: [B, ...]}) their looks."""
    if looks is None and self.shifted:
      set_look(self.model, self.own, 0)
    self.shifted = looks is not None
    for i in ids:
      if looks is not None:
        set_look(self.model, looks, i)
      self.data.qpos[:] = qpos[i]
      mujoco.mj_kinematics(self.model, self.data)
      mujoco.mj_camlight(self.model, self.data)
      for cam, cid in zip(self.cameras, self.cam_ids):
        self.renderer.update_scene(self.data, cid, scene_option=self.option)
        out[cam][i] = self.renderer.render()

  def close(self) -> None:
    self.renderer.close()


def start(drawer_args: tuple) -> tuple[subprocess.Popen, Connection]:
  """Start a render process (`python -m envs.render_process`, not multiprocessing's spawn, which
  would import the caller's main module again) and hand it `drawer_args` (Drawer's arguments,
  pickled over a socket: for a LIBERO scene, its textures make that 250 MB)."""
  mine, theirs = socket.socketpair()
  root = str(Path(__file__).resolve().parent.parent)  # where `envs` is imported from
  path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
  with theirs:
    proc = subprocess.Popen([sys.executable, "-m", "envs.render_process", str(theirs.fileno())],
                            pass_fds=(theirs.fileno(),), env={**os.environ, "PYTHONPATH": path})
  conn = Connection(mine.detach())
  try:
    conn.send(drawer_args)
  except OSError:  # it died before reading them; the caller finds its exit code
    pass
  return proc, conn


def serve(conn: Connection) -> None:
  """A render process: receive a Drawer's arguments, make it and send ("ready", None) or ("error",
  its traceback); then, for each (qpos [n, nq], looks or None) received, send ("images",
  {camera: [n, H, W, 3]}) or ("error", traceback), until None arrives or the socket closes."""
  try:
    model, size, cameras, flags_off, hidden_groups, max_geom, look_fields = conn.recv()
    drawer = Drawer(model, size, cameras, flags_off, hidden_groups, max_geom, look_fields)
  except Exception:  # noqa: BLE001  the parent raises it, with the cause named
    conn.send(("error", traceback.format_exc()))
    return
  conn.send(("ready", None))
  try:
    while True:
      try:
        job = conn.recv()
      except EOFError:  # the parent is gone
        return
      if job is None:
        return
      qpos, looks = job
      try:
        out = {c: np.zeros((qpos.shape[0],) + tuple(size) + (3,), np.uint8) for c in drawer.cameras}
        drawer.draw(qpos, range(qpos.shape[0]), out, looks)
        conn.send(("images", out))
      except Exception:  # noqa: BLE001
        conn.send(("error", traceback.format_exc()))
  finally:
    drawer.close()


if __name__ == "__main__":
  serve(Connection(int(sys.argv[1])))

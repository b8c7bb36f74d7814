"""MuJoCo's OpenGL platform, picked before MuJoCo is imported: rendering needs no display.

MuJoCo reads MUJOCO_GL once, when it is imported; unset, it uses GLFW, which
needs a display and fails on a headless machine. envs/__init__.py calls
`choose_gl` before anything imports mujoco, so every entry point (the CLI,
python -m, notebooks, the Python API) renders offscreen as `make` does: EGL
where libEGL loads, else OSMesa, else GLFW, whose failure to start
(`renderer_error`) says what to install. A value the user set is kept.
"""

from __future__ import annotations

import ctypes
import os
import sys

_EGL = ("libEGL.so.1", "libEGL.so")
_OSMESA = ("libOSMesa.so.8", "libOSMesa.so.6", "libOSMesa.so")
INSTALL = ("MUJOCO_GL=egl (libEGL with a driver: `apt install libegl1 libegl-mesa0`, or the NVIDIA "
           "driver) or MUJOCO_GL=osmesa (`apt install libosmesa6`)")
_state = {"mujoco_first": False, "found": None}  # what choose_gl saw, for the error message


class RendererError(RuntimeError):
  """MuJoCo's OpenGL renderer could not start, or one of its threads died."""


def _loads(names) -> bool:
  for name in names:
    try:
      ctypes.CDLL(name)
      return True
    except OSError:
      pass
  return False


def choose_gl() -> str:
  """Set MUJOCO_GL when unset (Linux): 'egl' where libEGL loads, else 'osmesa'; returns the value
  MuJoCo will read ('' where it stays unset: GLFW, which needs a display)."""
  value = os.environ.get("MUJOCO_GL")
  if "mujoco" in sys.modules:  # too late: MuJoCo has read it already
    _state["mujoco_first"] = value is None
    return value or ""
  if value is None and sys.platform.startswith("linux"):
    told = os.environ.get("PYOPENGL_PLATFORM", "").lower()  # PyOpenGL's platform: MuJoCo's must match
    value = told if told in ("egl", "osmesa") else (
        "egl" if _loads(_EGL) else "osmesa" if _loads(_OSMESA) else None)
    _state["found"] = value
    if value:
      os.environ["MUJOCO_GL"] = value
  elif (value or "").strip().lower() == "osmesa" and not _loads(_OSMESA):
    # else `import mujoco` fails inside PyOpenGL with "'NoneType' object has no attribute 'glGetError'"
    raise ImportError("MUJOCO_GL=osmesa, but libOSMesa is not installed: `apt install libosmesa6`, "
                      "or use MUJOCO_GL=egl (`apt install libegl1 libegl-mesa0`)")
  return value or ""


def renderer_error(cause: BaseException | None, what: str = "could not start") -> RendererError:
  """A RendererError naming the platform, why it fails where that is known, and the fix."""
  gl = os.environ.get("MUJOCO_GL", "")
  facts = [f"MUJOCO_GL={gl}" if gl else "MUJOCO_GL unset, so GLFW"]
  if gl.lower() in ("", "glfw", "glx", "1", "on", "true", "enable", "enabled") \
     and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    facts.append("no DISPLAY, and GLFW needs one")
  if _state["mujoco_first"]:
    facts.append("mujoco was imported before envs, which picks MUJOCO_GL")
  elif _state["found"] is None and not gl:
    facts.append("neither libEGL nor libOSMesa was found")
  why = f": {type(cause).__name__}: {cause}" if cause is not None else ""
  return RendererError(f"MuJoCo's OpenGL renderer {what} ({'; '.join(facts)}){why}. Without a display, "
                       f"render with {INSTALL}; left unset, MUJOCO_GL is picked from those installed.")

"""Appearance shift (ours, issue 29): the same task drawn in other colours and light.

A test of the paper's claim that skills are scene-agnostic: an image policy
sees the table, the objects and the scene light in colours it was not
trained on, while the physics, and so the task, stays as it was. A "look" is
the set of visual model fields an environment is drawn with (`LOOK_FIELDS`);
the physics never reads them, so only the cameras' pixels change.

Each environment's look is drawn from its own reset key, folded with a
constant of its own (`_STREAM`) so that the draws are independent of the
reset's: trial i of an evaluation (reset key fold_in(PRNGKey(seed), i)) gets
the same look for every policy and at any batch size, and every trial
another. What changes, per trial:
- the table: any hue, a saturation in `TABLE_SATURATION` and a value in
  `TABLE_VALUE`, the first of `TABLE_CANDIDATES` draws at least
  `MIN_CONTRAST` (CIELAB distance) from every object's and the robot's
  colour (failing that, the farthest);
- each object (a body tree rooted at the world: a block, a bowl, the cabinet
  and its drawer together): its hue turned by up to `OBJECT_HUE_TURN` of a
  circle and its saturation and value scaled within `OBJECT_SATURATION` and
  `OBJECT_VALUE`. Small turns: tasks name objects by colour (the red block on
  the green one), and a red block must stay red for the task to stay the same;
- the scene light: diffuse, ambient and specular scaled by one factor in
  `LIGHT_SCALE` and tinted per channel within `LIGHT_TINT`.
What stays: the robot's colours (the robot is the same in every scene; the
light still changes how it looks), the camera-attached headlight (MuJoCo
Warp's ray caster fixes it per render context, so it cannot vary per trial
there), and the background beyond the table (no skybox or walls: the
renderer's black).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

APPEARANCES = ("default", "shifted")
# The visual fields a look sets, named as in mujoco.MjModel and mjx.Model.
LOOK_FIELDS = ("geom_rgba", "light_ambient", "light_diffuse", "light_specular")
_STREAM = 0x5CE7E  # folded into a reset key: the look's draws, apart from the reset's own

TABLE_SATURATION = (0.1, 0.5)
TABLE_VALUE = (0.3, 0.85)
TABLE_CANDIDATES = 64
MIN_CONTRAST = 30.0  # CIELAB distance (dE76; 2.3 is just noticeable) from the table to anything on it
OBJECT_HUE_TURN = 0.05  # of a full circle, either way (18 degrees)
OBJECT_SATURATION = (0.8, 1.2)
OBJECT_VALUE = (0.8, 1.2)
LIGHT_SCALE = (0.5, 1.3)
LIGHT_TINT = (0.9, 1.1)


def check(appearance: str) -> str:
  """`appearance`, if it is one of APPEARANCES; else a ValueError naming them."""
  if appearance not in APPEARANCES:
    raise ValueError(f"unknown appearance {appearance!r}; valid appearances: {', '.join(APPEARANCES)}")
  return appearance


@dataclasses.dataclass(frozen=True)
class Parts:
  """What a look recolours, read once from the model."""
  geom_rgba: np.ndarray  # [ngeom, 4] the model's colours
  table: int  # the table's geom id
  object_of: np.ndarray  # [ngeom] int: the geom's object (0..n_objects-1), -1 for the table and the robot
  n_objects: int
  lights: dict  # {light_ambient, light_diffuse, light_specular: [nlight, 3]}


def parts(model: mujoco.MjModel, robot_root: str = "base", table: str = "table") -> Parts:
  """The table geom, the objects' geoms grouped by the body tree they belong to, and the lights."""
  root = model.body_rootid[model.geom_bodyid]
  robot = model.body(robot_root).id
  table_id = model.geom(table).id
  is_object = (root != robot) & (np.arange(model.ngeom) != table_id)
  roots = np.unique(root[is_object])
  object_of = np.where(is_object, np.searchsorted(roots, root), -1)
  recoloured = (object_of >= 0) | (np.arange(model.ngeom) == table_id)
  with_material = np.flatnonzero(recoloured & (model.geom_matid >= 0))
  if with_material.size:  # a material's colour would override the geom's
    raise ValueError(f"appearance shift recolours geoms by geom_rgba; geom {int(with_material[0])} has a material")
  return Parts(geom_rgba=np.array(model.geom_rgba, np.float32), table=int(table_id), object_of=object_of,
               n_objects=len(roots),
               lights={f: np.array(getattr(model, f), np.float32) for f in LOOK_FIELDS[1:]})


def looks(p: Parts, keys: jax.Array) -> dict:
  """Each environment's look ({field: [B, ...]} as in LOOK_FIELDS), drawn from its reset key
  (keys [B, 2]). Jitted once per task's shapes: batches of the same task share the compiled draw."""
  return _looks(keys, p.geom_rgba, p.object_of, p.lights, table=p.table, n_objects=p.n_objects)


def looks_fn(model: mujoco.MjModel):
  """keys [B, 2] -> `looks` of the model's parts."""
  return functools.partial(looks, parts(model))


@functools.partial(jax.jit, static_argnames=("table", "n_objects"))
def _looks(keys, geom_rgba, object_of, lights, table: int, n_objects: int) -> dict:
  return jax.vmap(lambda k: _look(k, geom_rgba, object_of, lights, table, n_objects))(keys)


def _look(key, base, object_of, lights, table: int, n_objects: int) -> dict:
  """One environment's look."""
  k_hue, k_sat, k_val, k_table, k_scale, k_tint = jax.random.split(jax.random.fold_in(key, _STREAM), 6)
  n = max(n_objects, 1)
  turn = jax.random.uniform(k_hue, (n,), minval=-OBJECT_HUE_TURN, maxval=OBJECT_HUE_TURN)
  sat = jax.random.uniform(k_sat, (n,), minval=OBJECT_SATURATION[0], maxval=OBJECT_SATURATION[1])
  val = jax.random.uniform(k_val, (n,), minval=OBJECT_VALUE[0], maxval=OBJECT_VALUE[1])
  h, s, v = jnp.moveaxis(rgb_to_hsv(base[:, :3]), -1, 0)
  obj = jnp.maximum(object_of, 0)
  shifted = hsv_to_rgb(jnp.stack([(h + turn[obj]) % 1.0, jnp.clip(s * sat[obj], 0.0, 1.0),
                                  jnp.clip(v * val[obj], 0.0, 1.0)], -1))
  rgb = jnp.where((object_of >= 0)[:, None], shifted, base[:, :3])
  # The table: the first candidate far enough from everything else, else the farthest.
  lo = jnp.array([0.0, TABLE_SATURATION[0], TABLE_VALUE[0]])
  hi = jnp.array([1.0, TABLE_SATURATION[1], TABLE_VALUE[1]])
  candidates = hsv_to_rgb(jax.random.uniform(k_table, (TABLE_CANDIDATES, 3), minval=lo, maxval=hi))
  others = np.arange(base.shape[0]) != table
  dist = jnp.linalg.norm(cielab(candidates)[:, None] - cielab(rgb)[None], axis=-1)
  nearest = jnp.min(jnp.where(others[None], dist, jnp.inf), axis=1)
  ok = nearest >= MIN_CONTRAST
  pick = jnp.where(ok.any(), jnp.argmax(ok), jnp.argmax(nearest))
  rgb = rgb.at[table].set(candidates[pick])
  scale = jax.random.uniform(k_scale, (), minval=LIGHT_SCALE[0], maxval=LIGHT_SCALE[1])
  tint = jax.random.uniform(k_tint, (3,), minval=LIGHT_TINT[0], maxval=LIGHT_TINT[1])
  out = {"geom_rgba": jnp.concatenate([rgb, base[:, 3:]], -1).astype(jnp.float32)}
  out.update({f: (light * scale * tint).astype(jnp.float32) for f, light in lights.items()})
  return out


def rgb_to_hsv(rgb: jax.Array) -> jax.Array:
  """[..., 3] RGB in [0, 1] -> HSV in [0, 1] (hue as a fraction of a circle)."""
  r, g, b = jnp.moveaxis(rgb, -1, 0)
  v = jnp.max(rgb, -1)
  c = v - jnp.min(rgb, -1)
  safe = jnp.where(c > 0, c, 1.0)
  h = jnp.where(v == r, ((g - b) / safe) % 6.0, jnp.where(v == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0))
  h = jnp.where(c > 0, h / 6.0, 0.0)
  s = jnp.where(v > 0, c / jnp.where(v > 0, v, 1.0), 0.0)
  return jnp.stack([h, s, v], -1)


def cielab(rgb: jax.Array) -> jax.Array:
  """[..., 3] sRGB in [0, 1] -> CIELAB (D65), where distance follows perceived difference."""
  linear = jnp.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
  to_xyz = jnp.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
  xyz = linear @ to_xyz.T / jnp.array([0.95047, 1.0, 1.08883])
  eps = (6 / 29) ** 3
  f = jnp.where(xyz > eps, jnp.cbrt(jnp.maximum(xyz, eps)), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
  fx, fy, fz = jnp.moveaxis(f, -1, 0)
  return jnp.stack([116 * fy - 16, 500 * (fx - fy), 200 * (fy - fz)], -1)


def hsv_to_rgb(hsv: jax.Array) -> jax.Array:
  """[..., 3] HSV in [0, 1] -> RGB in [0, 1]."""
  h, s, v = jnp.moveaxis(hsv, -1, 0)
  k = (jnp.array([5.0, 3.0, 1.0]) + h[..., None] * 6.0) % 6.0
  return v[..., None] - (v * s)[..., None] * jnp.clip(jnp.minimum(k, 4.0 - k), 0.0, 1.0)

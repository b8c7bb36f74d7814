"""Initial states for demonstrations, drawn by LIBERO's own placement samplers, apart from the
benchmark's 50 fixed init states (which evaluation uses: trial i = init state i).

A policy evaluated on the benchmark's init states should not have been taught from them: LIBERO's
own demonstrations (human teleoperation, not downloadable here) start from other placements. We
draw ours as LIBERO's `env.reset()` draws a placement, with its samplers and BDDL regions, in the
reference environment (`scene.reference_env`), with one change: the fixtures (cabinets, stoves,
racks), which LIBERO re-samples at every reset and which are not part of a state, are pinned where
our scene has them (`scene.py`: the evaluation's first reset). The movable objects are drawn
around them by LIBERO's code. A draw in which an object intersects another object or a fixture by more than
`MAX_PENETRATION` (possible since the fixture is no longer where the draw avoided it) is
rejected and the next reset drawn.

Draws are seeded (`np.random.seed`, as LIBERO's `env.seed`) and sequential, so the first n states
of a seed are the same whatever n; they are cached beside the scene (the reference env costs
5-10 s to build and ~0.1 s a reset).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import mujoco
import numpy as np

from envs.libero import scene as scenes
from envs.libero import suites

MAX_PENETRATION = 0.005  # m: deeper contacts between bodies at a drawn start reject it
MAX_TRIES = 20  # resets per kept start before giving up


def _cache_path(s: scenes.Scene, seed: int) -> Path:
  return s.xml_path.with_name(f"{s.xml_path.stem}.starts_seed{seed}.npy")


def starts(suite: str, which: int | str, n: int, seed: int = 0, progress: bool = False) -> np.ndarray:
  """[n, 1 + nq + nv] initial states of a task (LIBERO's flattened layout, as `suites.init_states`)
  drawn by LIBERO's samplers with the fixtures pinned; the first n of `seed`'s sequence."""
  if n < 1:
    raise ValueError(f"n must be >= 1, got {n}")
  s = scenes.scene(suite, which)
  path = _cache_path(s, seed)
  have = 0
  if path.exists():
    cached = np.load(path)
    if cached.shape[1] == s.meta["state_width"]:
      if len(cached) >= n:
        return cached[:n]
      have = len(cached)
  # The sequence is drawn again from its seed; asking for at least twice what the cache held keeps
  # a caller that asks for a few more at a time (demos.py's batches) from redrawing it each time.
  drawn = _draw(s, max(n, 2 * have), seed, progress)
  tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.npy")
  np.save(tmp, drawn)
  os.replace(tmp, path)
  return drawn[:n]


@contextlib.contextmanager
def _fixtures_pinned(env, poses: dict):
  """LIBERO's samplers, except that a sampler of fixtures only returns their pinned poses."""
  inner = env.env
  classes = {type(smp) for smp in inner.placement_initializer.samplers.values()}
  originals = {cls: cls.sample for cls in classes}

  def pinned(original):
    def sample(self, fixtures=None, reference=None, on_top=True):
      objs = list(self.mujoco_objects)
      if objs and all(o.root_body in poses for o in objs):
        return {o.name: (np.array(poses[o.root_body]["pos"]), np.array(poses[o.root_body]["quat"]), o) for o in objs}
      return original(self, fixtures=fixtures, reference=reference, on_top=on_top)
    return sample

  for cls, original in originals.items():
    cls.sample = pinned(original)
  try:
    yield
  finally:
    for cls, original in originals.items():
      cls.sample = original


def penetration(model: mujoco.MjModel, data: mujoco.MjData, movable: set[int], fixtures: set[int]) -> float:
  """The deepest contact (m, >= 0) in `data`'s current state between a movable object and another
  movable object or a fixture (the root bodies given). Contacts with the table or the floor do not
  count: LIBERO's draws sink objects into them by up to 4 cm (the benchmark's LIBERO-Object init
  states too), and the settling steps raise them."""
  deepest = 0.0
  for c in data.contact[:data.ncon]:
    r1, r2 = _root(model, int(model.geom_bodyid[c.geom1]), movable | fixtures), \
        _root(model, int(model.geom_bodyid[c.geom2]), movable | fixtures)
    if r1 != r2 and r1 >= 0 and r2 >= 0 and (r1 in movable or r2 in movable):
      deepest = max(deepest, -float(c.dist))
  return deepest


def _root(model: mujoco.MjModel, body: int, roots: set[int]) -> int:
  """The root in `roots` of `body`'s chain, or -1."""
  while body not in roots and body != 0:
    body = int(model.body_parentid[body])
  return body if body in roots else -1


def _draw(s: scenes.Scene, n: int, seed: int, progress: bool) -> np.ndarray:
  fixtures = {o["body"] for o in s.meta["objects"].values() if o["kind"] == "fixture"}
  poses = {b: p for b, p in s.meta["body_overrides"].items() if b in fixtures}
  model = scenes.model(s)
  data = mujoco.MjData(model)
  movable = {model.body(o["body"]).id for o in s.meta["objects"].values() if o["kind"] == "object"}
  fixed = {model.body(b).id for b in fixtures}
  env = scenes.reference_env(s.task.suite, s.task.index)
  out = []
  try:
    with _fixtures_pinned(env, poses):
      env.seed(seed)
      tries = 0
      while len(out) < n:
        if tries >= MAX_TRIES * n:
          raise RuntimeError(f"{s.task.suite} task {s.task.index}: {tries} draws gave only {len(out)} starts "
                             f"without an object intersecting a body by more than {MAX_PENETRATION} m")
        tries += 1
        env.reset()
        ref = env.env.sim.model._model
        moved = [b for b, p in poses.items() if not np.allclose(ref.body(b).pos, p["pos"], atol=1e-12)]
        if moved:
          raise RuntimeError(f"{s.task.suite} task {s.task.index}: fixtures {moved} not pinned by the sampler patch "
                             "(LIBERO places them another way)")
        state = np.asarray(env.env.sim.get_state().flatten(), np.float64)
        scenes.set_init_state(model, data, state)
        if penetration(model, data, movable, fixed) <= MAX_PENETRATION:
          out.append(state)
          if progress:
            print(f"{s.task.suite} {s.task.index}: start {len(out)}/{n}", flush=True)
  finally:
    env.close()
  return np.stack(out)


def check_distinct(suite: str, which: int | str, drawn: np.ndarray) -> float:
  """The smallest distance (m) between the movable objects' positions in a drawn start and in any
  of the benchmark's init states: > 0 when no drawn start is a benchmark one."""
  s = scenes.scene(suite, which)
  bench = suites.init_states(suite, which)
  adr = [o["joints"][0]["qposadr"] for o in s.meta["objects"].values()
         if o["kind"] == "object" and o["joints"] and o["joints"][0]["type"] == "free"]
  pos = lambda st: np.concatenate([st[:, 1 + a:4 + a] for a in adr], axis=1)  # noqa: E731
  d = np.linalg.norm(pos(drawn)[:, None] - pos(bench)[None], axis=-1)
  return float(d.min())

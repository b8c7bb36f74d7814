"""Scripted experts for LIBERO's pick-and-place goals, batched, from privileged object poses.

A goal whose atoms are all In(object, region) or On(object, region | object) of objects with a
free joint is done atom by atom by one state machine per environment: above the object, down,
close, lift, carry over the target, down, open, up. The hand keeps the reset pose's downward
orientation, turned about the vertical so that the fingers close across the object's shorter
horizontal side. Grasp and release heights come from the object's box (its collision geoms in
its body frame, a task constant) at its current pose. Actions are LIBERO's: the position error
over the controller's 5 cm scale and the orientation error over its 0.5 rad, clipped to [-1, 1].

Open, Close, TurnOn and TurnOff atoms (drawers, the microwave's door, the stove's knob) and the
dragged plate are `envs.libero.articulated`'s steps; the order of all steps is its `plan`.
`Expert` names an atom neither scripts.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from envs.libero import articulated
from envs.libero import engine as engines
from envs.libero import predicates

ABOVE, DESCEND, CLOSE, LIFT, CARRY, LOWER, RELEASE, RETREAT, DONE = range(9)
PHASES = ("above", "descend", "close", "lift", "carry", "lower", "release", "retreat", "done")
CLEARANCE = 0.08  # m above the object's top before descending
GRASP_DEPTH = 0.03  # m below the object's top, at most half its height
LIFT_CLEARANCE = 0.12  # m above the higher of the object's and the target's tops while carrying
RELEASE_ABOVE = 0.03  # m between the object's bottom and the target's top (On) when opened
# The Panda hand in the grip site's frame (robosuite's model, measured from its collision geoms):
# the fingers close along the site's x axis, the palm's bottom is 2.6 cm above the site and the
# palm reaches 10.5 cm either side along the fingers, 3.2 cm across.
PALM_ABOVE, PALM_HALF_LENGTH, PALM_HALF_WIDTH = 0.026, 0.105, 0.032
MAX_GRASP_WIDTH = 0.07  # m: an object side the open fingers (8 cm apart) close across
CLOSE_STEPS = 10
RELEASE_STEPS = 8
PHASE_LIMIT = 60  # control steps before a phase gives up waiting and moves on
HOLD_STEPS = 10  # control steps (0.5 s) the goal must keep holding after the expert is done


@dataclasses.dataclass(frozen=True)
class Task:
  """One pick-and-place atom resolved to ids: which object, onto or into what."""
  atom: predicates.Atom
  body: int
  box: np.ndarray  # [2, 3] the object's collision box in its body frame (min, max)
  target_body: int = -1  # On(object): the target's body ...
  target_box: np.ndarray | None = None  # ... and its box
  site: int = -1  # In/On(region): the region's site


def _box(model: mujoco.MjModel, body: int) -> np.ndarray:
  """[2, 3] min and max corners of a body's (and its subtree's) colliding geoms, in its frame."""
  corners = []
  for g in range(model.ngeom):
    b = int(model.geom_bodyid[g])
    while b not in (body, 0):
      b = int(model.body_parentid[b])
    if b != body or not (model.geom_contype[g] or model.geom_conaffinity[g]):
      continue
    center, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
    signs = np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T
    local = center + signs * half  # geom frame
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.geom_quat[g])
    pts = local @ rot.reshape(3, 3).T + model.geom_pos[g]
    b, chain = int(model.geom_bodyid[g]), []
    while b != body:  # up to the object's body
      chain.append(b)
      b = int(model.body_parentid[b])
    for c in chain:
      r = np.zeros(9)
      mujoco.mju_quat2Mat(r, model.body_quat[c])
      pts = pts @ r.reshape(3, 3).T + model.body_pos[c]
    corners.append(pts)
  if not corners:
    raise ValueError(f"body {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)} has no colliding geom")
  pts = np.concatenate(corners)
  return np.stack([pts.min(0), pts.max(0)])


def _world_box(box: np.ndarray, pos: np.ndarray, mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(lower, upper) [B, 3] world bounds of a body box at poses pos [B, 3], mat [B, 3, 3]."""
  signs = np.array(np.meshgrid(*[[0, 1]] * 3)).reshape(3, -1).T
  corners = np.where(signs[None] == 0, box[0], box[1])[0]  # [8, 3]
  world = np.einsum("bij,kj->bki", mat, corners) + pos[:, None]
  return world.min(1), world.max(1)


class Expert:
  """A batched pick-and-place expert for one scene's goal (its atoms in order)."""

  def __init__(self, batch: engines.LiberoBatch):
    self.batch = batch
    model, meta = batch.model, batch.scene.meta
    self.tasks = []
    steps = {}  # plan index -> articulated.Step: done by self.articulated
    for kind, atom in articulated.plan(batch):
      if kind != articulated.PLACE:
        steps[len(self.tasks)] = articulated.make_step(batch, kind, atom)
        self.tasks.append(steps[len(self.tasks)])
        continue
      if atom.test not in ("in_region", "on_region", "on_object"):
        raise NotImplementedError(f"{meta['task']}: no scripted expert for {atom.predicate}{atom.args} yet "
                                  "(envs/libero/expert.py scripts In and On of a movable object)")
      kw = dict(atom=atom, body=atom.body, box=_box(model, atom.body))
      if atom.test == "on_object":
        kw.update(target_body=atom.target_body, target_box=_box(model, atom.target_body))
      else:
        kw.update(site=atom.site)
      self.tasks.append(Task(**kw))
    fingers = [int(model.jnt_bodyid[model.joint(j["name"]).id]) for j in meta["robot"]["gripper_joints"]]
    self._fingers = fingers
    bodies = {model.body(o["body"]).id for o in meta["objects"].values()}
    self._obstacles = {b: _box(model, b) for b in sorted(bodies)}  # what the palm must clear
    n = batch.num_envs
    self.task = np.zeros(n, np.int64)  # which atom each env works on
    self.phase = np.zeros(n, np.int64)
    self.count = np.zeros(n, np.int64)
    self.goal_ori = np.zeros((n, 3, 3))
    self.offset = np.zeros((n, 3))  # object centre - hand, measured after the lift
    self.grasp_xy = np.zeros((n, 2))  # grasp point - object centre, chosen when the approach starts
    self.carry_z = np.zeros(n)  # the hand's carrying height, fixed when the lift starts
    self.fresh = np.ones(n, bool)
    self.articulated = articulated.Articulated(self, steps)

  # ---------------------------------------------------------------- what the expert reads

  def _hand(self):
    a, p = self.batch.data, self.batch.params
    return a["site_xpos"][:, p.eef_site].copy(), a["site_xmat"][:, p.eef_site].reshape(-1, 3, 3).copy()

  def _object(self, t: Task, ids: np.ndarray):
    a = self.batch.data
    lo, hi = _world_box(t.box, a["xpos"][ids, t.body], a["xmat"][ids, t.body].reshape(-1, 3, 3))
    return lo, hi

  def _target(self, t: Task, ids: np.ndarray):
    """(centre xy [n, 2], top z [n], kind) of the place target."""
    a = self.batch.data
    if t.target_body >= 0:
      lo, hi = _world_box(t.target_box, a["xpos"][ids, t.target_body], a["xmat"][ids, t.target_body].reshape(-1, 3, 3))
      return (lo[:, :2] + hi[:, :2]) / 2, hi[:, 2]
    site = a["site_xpos"][ids, t.site]
    size = np.asarray(t.atom.size)
    if t.atom.test == "in_region":  # the object's centre into the box: aim at its middle
      return site[:, :2], site[:, 2]
    return site[:, :2], site[:, 2] + size[2]

  def _grasp_plan(self, t: Task, ids: np.ndarray, hand_mat: np.ndarray, centre: np.ndarray, grasp_z: np.ndarray):
    """(hand orientation [n, 3, 3], grasp point - object centre [n, 2]): the fingers close across
    a side of the object that fits between them, at a point along its other side where the
    palm keeps the most room from every other object standing above the palm's height."""
    a = self.batch.data
    mat = a["xmat"][ids, t.body].reshape(-1, 3, 3)
    extent = t.box[1] - t.box[0]
    fingers = a["xpos"][ids, self._fingers[0]] - a["xpos"][ids, self._fingers[1]]
    f = fingers[:, :2] / np.maximum(np.linalg.norm(fingers[:, :2], axis=-1, keepdims=True), 1e-9)
    candidates = []  # (finger axis [n, 2], offset [n, 2], penalty)
    for across in (0, 1):
      if extent[across] > MAX_GRASP_WIDTH and not (across == int(np.argmin(extent[:2]))):
        continue
      along = 1 - across
      axis = mat[:, :2, across]
      axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
      other = mat[:, :2, along]
      other = other / np.maximum(np.linalg.norm(other, axis=-1, keepdims=True), 1e-9)
      reach = max(extent[along] / 2 - 0.015, 0.0)
      for frac in (0.0, -0.5, 0.5, -1.0, 1.0):
        candidates.append((axis, other * frac * reach, 0.002 * abs(frac) + 0.001 * (extent[across] > extent[along])))
    best_score = np.full(len(ids), -np.inf)
    best_axis, best_offset = np.zeros((len(ids), 2)), np.zeros((len(ids), 2))
    u = np.linspace(-PALM_HALF_LENGTH, PALM_HALF_LENGTH, 9)
    v = np.linspace(-PALM_HALF_WIDTH, PALM_HALF_WIDTH, 3)
    palm_z = grasp_z + PALM_ABOVE
    for axis, offset, penalty in candidates:
      normal = np.stack([-axis[:, 1], axis[:, 0]], -1)
      points = (centre[:, None, None, :2] + offset[:, None, None] + u[None, :, None, None] * axis[:, None, None]
                + v[None, None, :, None] * normal[:, None, None]).reshape(len(ids), -1, 2)
      clearance = np.full(len(ids), 1.0)
      for body, box in self._obstacles.items():
        if body == t.body:
          continue
        lo, hi = _world_box(box, a["xpos"][ids, body], a["xmat"][ids, body].reshape(-1, 3, 3))
        gap = np.maximum(np.maximum(lo[:, None, :2] - points, points - hi[:, None, :2]), 0.0)
        dist = np.linalg.norm(gap, axis=-1).min(axis=1)
        clearance = np.where(hi[:, 2] > palm_z, np.minimum(clearance, dist), clearance)
      score = np.minimum(clearance, 0.03) - penalty  # beyond 3 cm, room is room
      better = score > best_score
      best_score = np.where(better, score, best_score)
      best_axis[better], best_offset[better] = axis[better], offset[better]
    angle = np.arctan2(f[:, 0] * best_axis[:, 1] - f[:, 1] * best_axis[:, 0], (f * best_axis).sum(-1))
    angle = (angle + np.pi / 2) % np.pi - np.pi / 2  # the fingers are symmetric: turn the least
    c, s = np.cos(angle), np.sin(angle)
    rz = np.zeros((len(ids), 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    return rz @ hand_mat, best_offset

  # ---------------------------------------------------------------- one control step

  def act(self) -> np.ndarray:
    """LIBERO actions [B, 7] for the batch's current state; advances the state machines."""
    n = self.batch.num_envs
    hand, hand_mat = self._hand()
    target = hand.copy()
    grip = np.full(n, -1.0)
    for k, t in enumerate(self.tasks):
      ids = np.flatnonzero(self.task == k)
      if not ids.size or not isinstance(t, Task):  # articulated steps: self.articulated below
        continue
      lo, hi = self._object(t, ids)
      centre = (lo + hi) / 2
      place_xy, place_top = self._target(t, ids)
      phase = self.phase[ids]
      height = hi[:, 2] - lo[:, 2]
      grasp_z = hi[:, 2] - np.minimum(GRASP_DEPTH, height / 2)
      start = self.fresh[ids] & (phase == ABOVE)
      if start.any():
        sel = ids[start]
        self.goal_ori[sel], self.grasp_xy[sel] = self._grasp_plan(t, sel, hand_mat[sel], centre[start], grasp_z[start])
      grasp_xy = centre[:, :2] + self.grasp_xy[ids]
      carry_z = self.carry_z[ids]
      tgt = hand[ids].copy()
      g = np.full(ids.size, -1.0)
      sel = phase == ABOVE
      tgt[sel] = np.c_[grasp_xy[sel], hi[sel, 2] + CLEARANCE]
      sel = phase == DESCEND
      tgt[sel] = np.c_[grasp_xy[sel], grasp_z[sel]]
      sel = phase == CLOSE
      g[sel] = 1.0
      tgt[sel] = np.c_[grasp_xy[sel], grasp_z[sel]]
      sel = phase == LIFT
      g[sel] = 1.0
      tgt[sel, 2] = carry_z[sel]
      sel = phase == CARRY
      g[sel] = 1.0
      tgt[sel] = np.c_[place_xy[sel] - self.offset[ids[sel], :2], carry_z[sel]]
      sel = phase == LOWER
      g[sel] = 1.0
      below = hand[ids[sel], 2] - lo[sel, 2]  # the hand's height over the object's bottom
      if t.atom.test == "in_region":
        z = place_top[sel] + (hand[ids[sel], 2] - centre[sel, 2])
      else:
        z = place_top[sel] + RELEASE_ABOVE + below
      tgt[sel] = np.c_[place_xy[sel] - self.offset[ids[sel], :2], z]
      sel = phase == RELEASE
      tgt[sel] = hand[ids[sel]]
      sel = (phase == RETREAT) | (phase == DONE)
      tgt[sel, 2] = place_top[sel] + LIFT_CLEARANCE + height[sel]
      target[ids], grip[ids] = tgt, g

      err = np.linalg.norm(tgt - hand[ids], axis=-1)
      count = self.count[ids] + 1
      done = np.zeros(ids.size, bool)
      done |= (phase == ABOVE) & (err < 0.01)
      done |= (phase == DESCEND) & (err < 0.006)
      done |= (phase == CLOSE) & (count >= CLOSE_STEPS)
      done |= (phase == LIFT) & (np.abs(tgt[:, 2] - hand[ids, 2]) < 0.02)
      done |= (phase == CARRY) & (np.linalg.norm(tgt[:, :2] - hand[ids, :2], axis=-1) < 0.01)
      done |= (phase == LOWER) & (err < 0.008)
      done |= (phase == RELEASE) & (count >= RELEASE_STEPS)
      done |= (phase == RETREAT) & (err < 0.02)
      done |= (phase < DONE) & (count >= PHASE_LIMIT) & (phase != CLOSE) & (phase != RELEASE)
      closed = done & (phase == CLOSE)  # the object still where it lay: the height to carry it at
      self.carry_z[ids[closed]] = (np.maximum(hi[closed, 2], place_top[closed]) + LIFT_CLEARANCE
                                   + (hand[ids[closed], 2] - lo[closed, 2]))
      lifted = done & (phase == LIFT)
      self.offset[ids[lifted]] = centre[lifted] - hand[ids[lifted]]
      nxt = np.where(done, phase + 1, phase)
      last = nxt == DONE
      more = last & (k + 1 < len(self.tasks))  # next atom
      self.task[ids[more]] = k + 1
      nxt = np.where(more, ABOVE, nxt)
      self.phase[ids] = nxt
      self.count[ids] = np.where(done, 0, count)
      self.fresh[ids] = done
    self.articulated.act(hand, hand_mat, target, grip)
    pos = np.clip((target - hand) / 0.05, -1, 1)
    rot = np.clip(_rotation_error(self.goal_ori, hand_mat) / 0.5, -1, 1)
    return np.concatenate([pos, rot, grip[:, None]], axis=1)


def _rotation_error(desired: np.ndarray, current: np.ndarray) -> np.ndarray:
  """Axis-angle [B, 3] of desired @ current^T (world frame), the delta robosuite's goal applies."""
  r = desired @ np.swapaxes(current, -1, -2)
  cos = np.clip((np.trace(r, axis1=-2, axis2=-1) - 1) / 2, -1, 1)
  angle = np.arccos(cos)
  axis = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1)
  norm = np.linalg.norm(axis, axis=-1, keepdims=True)
  return np.where(norm > 1e-9, axis / np.maximum(norm, 1e-12) * angle[:, None], 0.0)


def run(suite: str, index: int, trials: int = 50, nthread: int = 0) -> dict:
  """The expert on `trials` benchmark init states of a task, as LIBERO evaluates: 10 settling
  no-ops, then up to the suite's time limit. A trial succeeds when the goal holds with the
  gripper open and the hand withdrawn (the state machine done), and still holds a moment later
  (`HOLD_STEPS` further steps, arm at rest): placed and released, not dropped on the way."""
  from envs.libero import scene as scenes, suites
  s = scenes.scene(suite, index)
  batch = engines.LiberoBatch(s, trials, nthread=nthread)
  batch.reset(suites.init_states(suite, index)[np.arange(trials) % suites.INIT_STATES_PER_TASK])
  settle = np.tile([0, 0, 0, 0, 0, 0, -1.0], (trials, 1))
  for _ in range(suites.SETTLE_STEPS):
    batch.step(settle)
  expert = Expert(batch)
  limit = suites.TIME_LIMITS[suite]
  first = np.full(trials, -1)  # the first step at which LIBERO's success holds
  held = np.zeros(trials, np.int64)  # steps the goal has held since the expert finished
  done = np.zeros(trials, bool)
  for k in range(limit + HOLD_STEPS):
    actions = expert.act()
    batch.step(actions if k < limit else np.where(np.arange(7) == 6, -1.0, 0.0) * np.ones((trials, 1)))
    ok = batch.success()
    first[(first < 0) & ok & (k < limit)] = k
    held = np.where(ok & (expert.phase == DONE), held + 1, 0)
    done |= (held >= HOLD_STEPS) & (first >= 0)
  return {"suite": suite, "task": index, "name": s.task.name, "trials": trials,
          "success": float(done.mean()), "libero_success": float((first >= 0).mean()),
          "median_steps": float(np.median(first[first >= 0])) if (first >= 0).any() else None,
          "time_limit": limit}


def main() -> None:
  import argparse
  import json
  from envs.libero import suites
  parser = argparse.ArgumentParser(description="The scripted LIBERO experts' success per task (B trials at once).")
  parser.add_argument("--suite", default="libero_object", choices=suites.SUITES)
  parser.add_argument("--tasks", default="all", help="comma-separated task indices, or all")
  parser.add_argument("--trials", type=int, default=50)
  parser.add_argument("--out", default=None, help="write the rows as JSON here")
  args = parser.parse_args()
  tasks = range(len(suites.tasks(args.suite))) if args.tasks == "all" else [int(t) for t in args.tasks.split(",")]
  rows = []
  for index in tasks:
    try:
      row = run(args.suite, index, args.trials)
    except NotImplementedError as e:
      row = {"suite": args.suite, "task": index, "name": suites.task(args.suite, index).name, "not_scripted": str(e)}
    rows.append(row)
    print(json.dumps(row), flush=True)
  if args.out:
    with open(args.out, "w") as f:
      json.dump(rows, f, indent=1)


if __name__ == "__main__":
  main()

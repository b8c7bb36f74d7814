"""Scripted experts for LIBERO's pick-and-place goals, batched, from privileged object poses.

A goal whose atoms are all In(object, region) or On(object, region | object) of objects with a
free joint is done atom by atom by one state machine per environment: above the object, down,
close, lift, carry over the target, down, open, up. The hand keeps the reset pose's downward
orientation, turned about the vertical so that the fingers close across the object's shorter
horizontal side; an object that fits an In region's box only turned is turned square to it while
carried (a book into a caddy's slot), and one that would fail the box standing on its container's
floor is set down leaning. Grasp and release heights come from the object's box (its collision
geoms in its body frame, a task constant) at its current pose. Actions are LIBERO's: the position error
over the controller's 5 cm scale and the orientation error over its 0.5 rad, clipped to [-1, 1].

Open, Close, TurnOn and TurnOff atoms (drawers, the microwave's door, the stove's knob), the
dragged plate and the mug pushed into the microwave are `envs.libero.articulated`'s steps, a tall
object put on a tilted board (the wine bottle on the rack) is laid down by `envs.libero.laydown`;
the order of all steps is `plan`'s.
`Expert` names an atom neither scripts.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from envs.libero import articulated
from envs.libero import engine as engines
from envs.libero import laydown
from envs.libero import predicates

ABOVE, DESCEND, CLOSE, LIFT, CARRY, LOWER, RELEASE, RETREAT, DONE = range(9)
PHASES = ("above", "descend", "close", "lift", "carry", "lower", "release", "retreat", "done")
CLEARANCE = 0.08  # m above the object's top before descending
GRASP_DEPTH = 0.03  # m below the object's top, at most half its height
LIFT_CLEARANCE = 0.12  # m above the higher of the object's and the target's tops while carrying
RELEASE_ABOVE = 0.03  # m between the object's bottom and the target's top (On) when opened
RIM_RELEASE_ABOVE = 0.015  # m: ... a rim-held object's, over the target's floor under it (a mug over a plate's
#                            floor, not its rim: dropped 4 cm, it tips onto the rim and off the plate's middle)
# The Panda hand in the grip site's frame (robosuite's model, measured from its collision geoms):
# the fingers close along the site's x axis, the palm's bottom is 3.1 cm above the site (its mesh's
# lowest vertex) and the
# palm reaches 10.5 cm either side along the fingers, 3.2 cm across.
PALM_ABOVE, PALM_HALF_LENGTH, PALM_HALF_WIDTH = 0.031, 0.105, 0.032
MAX_GRASP_WIDTH = 0.07  # m: an object side the open fingers (8 cm apart) close across
# An object wider than that both ways (a bowl, a mug) is grasped at its rim: the fingers close
# across its wall, radially, at the top of one of the colliding geoms that reach its top.
RIM_BAND = 0.005  # m: a geom whose top is this close to the object's top is part of the rim
RIM_DEPTH = 0.025  # m the grip site goes below the rim's top: the pads (site -4 to +12 mm) cover
#                    its top centimetre and the palm (2.6 cm above the site) stays clear of it
REACH_COST = 0.1  # score per metre of the rim point from the shoulder: the near side of a far
#                   bowl keeps the elbow off its limit (the arm is straight 0.8 m out)
TIPPED_COST = 1.0  # score per metre a rim point lies below the rim's highest (a bowl leaning over)
RIM_CARRY_STEP = 0.025  # m: the carry's target at most this far ahead of a rim-held object's hand
ABOVE_Z_TOLERANCE = 0.03  # m: above the grasp point is reached at this height error (at full
#                           reach the arm cannot lift the hand to the exact clearance height)
ABOVE_TURNED = 0.1  # rad: ... and the hand turned to the grasp's orientation this closely (it turns
#                     while it moves: a hand handed over by an articulated step is still turning back)
OPEN = 0.08  # m between the fingers' pads, open
FINGER_THICKNESS = 0.025  # m: a finger's outer face beyond its pad's (robosuite's finger collision mesh)
RIM_OPENING, NARROW_COST = 0.05, 0.003  # m: the fingers open this far only about a rim where the
#                                         open fingers would not fit (a bowl in a drawer)
OVERHANG_BAND = 0.005  # m: what hangs over an object's top (or reaches this far below it) ...
ESCAPE, SLIDE_RAISE = 0.02, 0.004  # ... the object slides this far out from under, this much up,
SLIDE_STEPS = 10  # control steps at most (a drawer's front wall may stop it), then goes up
OPENING_TOLERANCE = 0.004  # m: the fingers' opening is held within this of the planned one
FINGER_BELOW = 0.012  # m: the fingers' lowest point below the site
FINGER_HALF_WIDTH = 0.01  # m: the fingers across their closing axis
ROOM, FINGER_ROOM = 0.03, 0.02  # m: room around the palm (the fingers) beyond this is as good as more
FINGER_MARGIN, TIGHT_COST = 0.01, 3.0  # m: less room than this beside a finger is the hand's
#                                        positioning error (1-2 cm at full reach) from a collision
PALM_WEIGHT = 0.25  # the palm's room counts a quarter of the fingers' (they go lower, beside the object)
CLOSE_STEPS = 10  # the fingers close for at least this many steps ...
CLOSE_STEPS_MAX = 16  # ... and on until they stop (a bowl's 3 mm wall: the fingers travel 7 cm)
CLOSED_SPEED = 0.001  # m per step: the fingers have stopped on the object
RELEASE_STEPS = 8
STILL_SPEED, STILL_STEPS = 0.001, 5  # m per step: a lowered object this slow for this many steps rests
PHASE_LIMIT = 60  # control steps before a phase gives up waiting and moves on
HOLD_STEPS = 10  # control steps (0.5 s) the goal must keep holding after the expert is done
EMPTY_GAP = 0.004  # m: fingers this close together after closing hold nothing (the grasp missed)
TRAVERSE_CLEARANCE = 0.04  # m the hand's grip site keeps above what stands along its way to the next grasp
TRAVERSE_NEAR = 0.03  # m: this close (horizontally) to the grasp point the hand descends to the clearance height
SPOT_MARGIN = 0.02  # m: a spot in a region keeps the object's body this far inside the region's edge
SPOT_ROOM = 0.015  # m of room beyond the object's footprint from what stands in the region: more is as good
FIT_MARGIN = 0.005  # m: a held object's footprint fits a region's box with this much to spare on each side
CARRY_TURNED = 0.05  # rad: a carry that turns the held object ends this close to the turn
# LIBERO's In box can start above its container's floor (the caddy's back slot: 1.1 cm, less the
# test's 1 cm): an object whose body origin is below its own bottom (the book's, by 2 mm) fails it
# standing on that floor, and is set down leaning over the slot's lower wall instead.
LEAN_BELOW = 0.002  # m: an object whose body, upright on the floor, is not this far above the box's bottom leans
LEAN_TILT = 0.35  # rad the hand tips a leaned object, its foot toward the higher wall (it settles at ~19 deg)
WALL_PROBE = 0.01  # m beyond the region's side where its walls are looked for
# A lift close to the robot passes a singular arm: near the shoulder's height, the upper arm upright
# and the forearm folded straight down over a downward hand (joints 1 and 3, 5 and 7 in line), the
# elbow at its limit (-3.07 rad); the OSC cannot raise the hand and drifts it toward the base
# (LIBERO-10 7: the cream cheese 34 cm from the shoulder, 14 cm of drift, the carry stuck). The
# object is slid out on the table first, then lifted (not one held by its rim: see `act`).
WRIST_ABOVE = 0.2  # m: the Panda's wrist (link 6) above the grip site of a downward hand
REACH_MIN = 0.4  # m the lift keeps the wrist from the shoulder (beyond 0.4 m the elbow stayed under -2.77 rad)
REACH_SLIDE_STEPS = 30  # control steps at most for a slide out to REACH_MIN (1-2 cm a step)


@dataclasses.dataclass(frozen=True)
class Task:
  """One pick-and-place atom resolved to ids: which object, onto or into what."""
  atom: predicates.Atom
  body: int
  box: np.ndarray  # [2, 3] the object's collision box in its body frame (min, max)
  target_body: int = -1  # On(object): the target's body ...
  target_box: np.ndarray | None = None  # ... and its box
  site: int = -1  # In/On(region): the region's site
  rim: np.ndarray | None = None  # [k, 3] rim points (body frame) of an object grasped at its rim


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


def _geoms(model: mujoco.MjModel, bodies) -> dict[str, np.ndarray]:
  """The colliding geoms of the given bodies' subtrees as oriented boxes (their bounding boxes in
  their own frames): the owner (which of `bodies`), the geom's body, centre and rotation in that
  body's frame, half sizes. A cabinet's drawer or a basket is its walls, not its whole box."""
  owner, body, centre, rot, half = [], [], [], [], []
  for g in range(model.ngeom):
    if not (model.geom_contype[g] or model.geom_conaffinity[g]):
      continue
    b = int(model.geom_bodyid[g])
    while b not in bodies and b != 0:
      b = int(model.body_parentid[b])
    if b == 0:
      continue
    r = np.zeros(9)
    mujoco.mju_quat2Mat(r, model.geom_quat[g])
    owner.append(b)
    body.append(int(model.geom_bodyid[g]))
    centre.append(model.geom_pos[g] + r.reshape(3, 3) @ model.geom_aabb[g, :3])
    rot.append(r.reshape(3, 3))
    half.append(model.geom_aabb[g, 3:])
  return dict(owner=np.array(owner), body=np.array(body), centre=np.array(centre), rot=np.array(rot),
              half=np.array(half))


def _rim(model: mujoco.MjModel, body: int, box: np.ndarray) -> np.ndarray | None:
  """[k, 3] body-frame centres of the colliding boxes that reach the top of an object too wide for the
  fingers both ways (its rim: a bowl's or a mug's wall), or None for an object grasped across."""
  if (box[1, :2] - box[0, :2]).min() <= MAX_GRASP_WIDTH:
    return None
  points = []
  for g in range(model.ngeom):
    if model.geom_bodyid[g] != body or not (model.geom_contype[g] or model.geom_conaffinity[g]):
      continue
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.geom_quat[g])
    top = model.geom_pos[g, 2] + np.abs(rot.reshape(3, 3)[2] * model.geom_size[g]).sum()
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX and top > box[1, 2] - RIM_BAND:
      points.append(model.geom_pos[g].copy())
  return np.array(points) if len(points) >= 3 else None


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
    lays = {}  # plan index -> laydown.Step: done by self.laydown
    for kind, atom in articulated.plan(batch):
      if kind == laydown.LAY:
        lays[len(self.tasks)] = laydown.make_step(batch, atom)
        self.tasks.append(lays[len(self.tasks)])
        continue
      if kind != articulated.PLACE:
        steps[len(self.tasks)] = articulated.make_step(batch, kind, atom)
        self.tasks.append(steps[len(self.tasks)])
        continue
      if atom.test not in ("in_region", "on_region", "on_object"):
        raise NotImplementedError(f"{meta['task']}: no scripted expert for {atom.predicate}{atom.args} yet "
                                  "(envs/libero/expert.py scripts In and On of a movable object)")
      box = _box(model, atom.body)
      kw = dict(atom=atom, body=atom.body, box=box, rim=_rim(model, atom.body, box))
      if atom.test == "on_object":
        kw.update(target_body=atom.target_body, target_box=_box(model, atom.target_body))
      else:
        kw.update(site=atom.site)
      self.tasks.append(Task(**kw))
    fingers = [int(model.jnt_bodyid[model.joint(j["name"]).id]) for j in meta["robot"]["gripper_joints"]]
    self._fingers = fingers
    self._shoulder = int(model.jnt_bodyid[model.joint(meta["robot"]["arm_joints"][0]["name"]).id])
    bodies = {model.body(o["body"]).id for o in meta["objects"].values()}
    self._obstacles = _geoms(model, bodies)  # what the hand must clear
    n = batch.num_envs
    self.task = np.zeros(n, np.int64)  # which atom each env works on
    self.phase = np.zeros(n, np.int64)
    self.count = np.zeros(n, np.int64)
    self.goal_ori = np.zeros((n, 3, 3))
    self.offset = np.zeros((n, 3))  # object centre - hand, measured after the lift
    self.grasp_xy = np.zeros((n, 2))  # grasp point - object centre, chosen when the approach starts
    self.opening = np.full(n, OPEN)  # how far the fingers open for the approach
    self.carry_z = np.zeros(n)  # the hand's carrying height, fixed when the lift starts
    self.lift_xy, self.lift_z = np.zeros((n, 2)), np.zeros(n)  # where the lift starts going up
    self.slide_steps = np.full(n, SLIDE_STEPS)  # the most steps the slide there takes
    self.fresh = np.ones(n, bool)
    self.hand_z = np.zeros(n)  # the hand's height at the previous step
    self.still = np.zeros(n, np.int64)  # steps the hand has held still while lowering
    self.from_articulated = np.zeros(n, bool)  # handed over by an articulated step, the hand still turning back
    # the pick passes over what stands on its way (`_path_top`), except right after an articulated
    # step: the hand has backed off its fixture, and climbing over the opened cabinet costs the time
    # a drawer-then-place goal does not have (LIBERO-Goal 3)
    self.traverse = np.ones(n, bool)
    self.spot = np.zeros((n, 2))  # where in a region the object's centre goes - the region's centre
    self.lean = np.zeros((n, 2))  # the way a leaned object's top tips (toward the lower wall), or 0
    self.turned = np.zeros(n, bool)  # the carry turns the hand (the object square to a tight region)
    self._finger_q = [j["qposadr"] for j in meta["robot"]["gripper_joints"]]
    self.gap = np.zeros(n)  # the fingers' opening at the previous step
    self.articulated = articulated.Articulated(self, steps)
    self.laydown = laydown.LayDown(self, lays)

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
      return site[:, :2] + self.spot[ids], site[:, 2]
    return site[:, :2] + self.spot[ids], site[:, 2] + size[2]

  def _grasp_plan(self, t: Task, ids: np.ndarray, hand_mat: np.ndarray, centre: np.ndarray, grasp_z: np.ndarray,
                  at_rest: np.ndarray | None = None):
    """(hand orientation [n, 3, 3], grasp point - object centre [n, 2], finger opening [n]): the fingers close across
    a side of the object that fits between them, at a point along its other side where the
    palm keeps the most room from every other object standing above the palm's height.
    `hand_mat` is the orientation the plan turns from: the hand's, or (where `at_rest`) the reset
    pose's, for a hand still turning back from an articulated step."""
    a = self.batch.data
    mat = a["xmat"][ids, t.body].reshape(-1, 3, 3)
    extent = t.box[1] - t.box[0]
    fingers = a["xpos"][ids, self._fingers[0]] - a["xpos"][ids, self._fingers[1]]
    if at_rest is not None:  # the fingers close along the site's x axis
      fingers = np.where(at_rest[:, None], hand_mat[:, :, 0], fingers)
    f = fingers[:, :2] / np.maximum(np.linalg.norm(fingers[:, :2], axis=-1, keepdims=True), 1e-9)
    candidates = []  # (finger axis [n, 2], offset [n, 2], penalty)
    if t.rim is not None:  # across the wall at one of its rim points, the fingers radial
      middle = t.rim.mean(0)
      highest = (a["xpos"][ids, t.body, None] + np.einsum("bij,kj->bki", mat, t.rim))[..., 2].max(1)
      for point in t.rim:
        axis = np.einsum("bij,j->bi", mat, point - middle)[:, :2]
        axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
        world = a["xpos"][ids, t.body] + np.einsum("bij,j->bi", mat, point)
        drop = highest - world[:, 2]  # a tipped bowl is taken at its high side, where the grasp height is
        turn = np.abs(np.arcsin(np.clip(f[:, 0] * axis[:, 1] - f[:, 1] * axis[:, 0], -1, 1)))
        reach = np.linalg.norm(world[:, :2] - a["xpos"][ids, self._shoulder, :2], axis=-1)
        cost = 0.002 * turn / (np.pi / 2) + REACH_COST * reach + TIPPED_COST * drop
        candidates.append((axis, world[:, :2] - centre[:, :2], cost, OPEN))
        candidates.append((axis, world[:, :2] - centre[:, :2], cost + NARROW_COST, RIM_OPENING))
    for across in (0, 1) if t.rim is None else ():
      if extent[across] > MAX_GRASP_WIDTH and not (across == int(np.argmin(extent[:2]))):
        continue
      along = 1 - across
      axis = mat[:, :2, across]
      axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
      other = mat[:, :2, along]
      other = other / np.maximum(np.linalg.norm(other, axis=-1, keepdims=True), 1e-9)
      reach = max(extent[along] / 2 - 0.015, 0.0)
      for frac in (0.0, -0.5, 0.5, -1.0, 1.0):
        candidates.append((axis, other * frac * reach, 0.002 * abs(frac) + 0.001 * (extent[across] > extent[along]), OPEN))
    best_score = np.full(len(ids), -np.inf)
    best_axis, best_offset = np.zeros((len(ids), 2)), np.zeros((len(ids), 2))
    best_opening = np.full(len(ids), OPEN)
    u = np.linspace(-PALM_HALF_LENGTH, PALM_HALF_LENGTH, 9)
    v = np.linspace(-PALM_HALF_WIDTH, PALM_HALF_WIDTH, 3)
    palm_z, finger_z = grasp_z + PALM_ABOVE, grasp_z - FINGER_BELOW
    o = self._obstacles
    keep = o["owner"] != t.body
    bmat = a["xmat"][ids[:, None], o["body"][keep]].reshape(len(ids), -1, 3, 3)
    gpos = a["xpos"][ids[:, None], o["body"][keep]] + np.einsum("bgij,gj->bgi", bmat, o["centre"][keep])
    gmat = np.einsum("bgij,gjk->bgik", bmat, o["rot"][keep])
    half = o["half"][keep]
    top = gpos[..., 2] + np.einsum("bgj,gj->bg", np.abs(gmat[:, :, 2]), half)
    below_palm, below_tips = top < palm_z[:, None], top < finger_z[:, None]
    rise = np.array([0.0, 0.04, 0.08])  # the hand's column above its lowest points
    for axis, offset, penalty, opening in candidates:
      normal = np.stack([-axis[:, 1], axis[:, 0]], -1)
      grasp = centre[:, :2] + offset
      palm = (grasp[:, None, None] + u[None, :, None, None] * axis[:, None, None]
              + v[None, None, :, None] * normal[:, None, None]).reshape(len(ids), -1, 2)
      span = np.array([0.0, 0.5, 1.0]) * FINGER_THICKNESS + min(opening, OPEN) / 2  # inner face to outer
      along = np.concatenate([-span, span])
      tips = (grasp[:, None, None] + along[None, :, None, None] * axis[:, None, None]
              + np.array([-1, 0, 1])[None, None, :, None] * FINGER_HALF_WIDTH * normal[:, None, None]).reshape(len(ids), -1, 2)
      points = np.concatenate([
          np.concatenate([np.repeat(palm, 3, 1), (palm_z[:, None] + np.tile(rise, palm.shape[1]))[..., None]], -1),
          np.concatenate([np.repeat(tips, 3, 1), (finger_z[:, None] + np.tile(rise, tips.shape[1]))[..., None]], -1)], 1)
      local = np.einsum("bgji,bpgj->bpgi", gmat, points[:, :, None] - gpos[:, None])  # [n, points, geoms, 3]
      dist = np.linalg.norm(np.maximum(np.abs(local) - half, 0.0), axis=-1)  # [n, points, geoms]
      k = 3 * palm.shape[1]  # what stands lower than the palm (the fingers) is not in its way
      room_palm = np.minimum(np.where(below_palm[:, None], 1.0, dist[:, :k]).min(axis=(1, 2)), ROOM)
      room_tips = np.minimum(np.where(below_tips[:, None], 1.0, dist[:, k:]).min(axis=(1, 2)), FINGER_ROOM)
      score = room_tips + PALM_WEIGHT * room_palm - penalty - TIGHT_COST * np.maximum(FINGER_MARGIN - room_tips, 0.0)
      better = score > best_score
      best_score = np.where(better, score, best_score)
      best_axis[better], best_offset[better], best_opening[better] = axis[better], offset[better], opening
    angle = np.arctan2(f[:, 0] * best_axis[:, 1] - f[:, 1] * best_axis[:, 0], (f * best_axis).sum(-1))
    angle = (angle + np.pi / 2) % np.pi - np.pi / 2  # the fingers are symmetric: turn the least
    c, s = np.cos(angle), np.sin(angle)
    rz = np.zeros((len(ids), 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    return rz @ hand_mat, best_offset, best_opening

  def _escape(self, t: Task, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """[n, 2] where to slide a just-grasped object before lifting it: out from under whatever
    hangs over it (a bowl at the back of a drawer, half under the cabinet's top), or 0."""
    o = self._obstacles
    keep = o["owner"] != t.body
    a = self.batch.data
    bmat = a["xmat"][ids[:, None], o["body"][keep]].reshape(len(ids), -1, 3, 3)
    gpos = a["xpos"][ids[:, None], o["body"][keep]] + np.einsum("bgij,gj->bgi", bmat, o["centre"][keep])
    gmat = np.einsum("bgij,gjk->bgik", bmat, o["rot"][keep])
    half = o["half"][keep]
    bottom = gpos[..., 2] - np.einsum("bgj,gj->bg", np.abs(gmat[:, :, 2]), half)
    over = (bottom > hi[:, 2, None] - OVERHANG_BAND) & (bottom < hi[:, 2, None] + LIFT_CLEARANCE)
    grid = np.linspace(0.0, 1.0, 7)
    frac = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)
    points = lo[:, None, :2] + frac[None] * (hi - lo)[:, None, :2]  # the object's footprint [n, p, 2]
    diff = np.concatenate([points[:, :, None] - gpos[:, None, :, :2], np.zeros(points.shape[:2] + (gpos.shape[1], 1))], -1)
    local = np.einsum("bgji,bpgj->bpgi", gmat, diff)
    under = ((np.abs(local) <= half).all(-1) & over[:, None]).any(-1)  # [n, p]: footprint points covered
    middle = (lo[:, :2] + hi[:, :2]) / 2
    pull = middle - np.where(under[..., None], points, 0.0).sum(1) / np.maximum(under.sum(1), 1)[:, None]
    pull = pull / np.maximum(np.linalg.norm(pull, axis=-1, keepdims=True), 1e-9)
    return np.where(under.any(1)[:, None], pull * ESCAPE, 0.0)

  def _standing(self, t: Task | int, ids: np.ndarray):
    """(centre [n, g, 3], rotation [n, g, 3, 3], half [g, 3], top [n, g], bottom [n, g]) of the
    colliding boxes of every object but `t`'s (a task's, or a body id: an articulated step's fixture), in the world."""
    o, a = self._obstacles, self.batch.data
    keep = o["owner"] != (t if isinstance(t, (int, np.integer)) else t.body)
    bmat = a["xmat"][ids[:, None], o["body"][keep]].reshape(len(ids), -1, 3, 3)
    gpos = a["xpos"][ids[:, None], o["body"][keep]] + np.einsum("bgij,gj->bgi", bmat, o["centre"][keep])
    gmat = np.einsum("bgij,gjk->bgik", bmat, o["rot"][keep])
    half = o["half"][keep]
    reach = np.einsum("bgj,gj->bg", np.abs(gmat[:, :, 2]), half)
    return gpos, gmat, half, gpos[..., 2] + reach, gpos[..., 2] - reach

  def _floor(self, t: Task, ids: np.ndarray, xy: np.ndarray, top: np.ndarray) -> np.ndarray:
    """[n] the height an On(object) target holds an object up to at xy [n, 2]: the highest top of its
    colliding boxes there (a plate's floor, 1 cm under its rim), or its box's top `top` [n] if none."""
    gpos, gmat, half, tops, _ = self._standing(t, ids)
    owner = self._obstacles["owner"][self._obstacles["owner"] != t.body]
    under = (self._flat_distance(xy[:, None], gpos, gmat, half)[:, 0] < 1e-6) & (owner == t.target_body)
    floor = np.where(under, tops, -np.inf).max(-1)
    return np.where(np.isfinite(floor), floor, top)

  @staticmethod
  def _flat_distance(points: np.ndarray, gpos: np.ndarray, gmat: np.ndarray, half: np.ndarray) -> np.ndarray:
    """[n, p, g] horizontal distances from points [n, p, 2] to boxes (at their centres' heights)."""
    diff = np.concatenate([points[:, :, None] - gpos[:, None, :, :2], np.zeros(points.shape[:2] + (gpos.shape[1], 1))], -1)
    local = np.einsum("bgji,bpgj->bpgi", gmat, diff)
    return np.linalg.norm(np.maximum(np.abs(local) - half, 0.0), axis=-1)

  def _path_top(self, t: Task | int, ids: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """[n] the highest top of what stands within the palm's reach of the hand's way from `start` to
    `end` [n, 2] (a basket just filled, beside the next object): the hand passes over it, not
    through its wall dragging it along."""
    gpos, gmat, half, top, _ = self._standing(t, ids)
    frac = np.linspace(0.0, 1.0, 8)
    points = start[:, None] + frac[None, :, None] * (end - start)[:, None]
    near = (self._flat_distance(points, gpos, gmat, half) < PALM_HALF_LENGTH).any(1)  # [n, g]
    return np.where(near, top, -np.inf).max(-1)

  def _reach_out(self, ids: np.ndarray, tgt: np.ndarray, top: np.ndarray) -> np.ndarray:
    """[n, 3] hand goals `tgt` moved out horizontally from the shoulder until the wrist is REACH_MIN
    from it at every height of the hand from the goal's up to `top` [n] (the lift's way up): a lift
    near the robot's base otherwise passes the singular folded arm."""
    shoulder = self.batch.data["xpos"][ids, self._shoulder]
    low, high = tgt[:, 2] + WRIST_ABOVE - shoulder[:, 2], np.maximum(top, tgt[:, 2]) + WRIST_ABOVE - shoulder[:, 2]
    dz = np.where((low <= 0) & (high >= 0), 0.0, np.minimum(np.abs(low), np.abs(high)))  # the nearest height
    need = np.sqrt(np.maximum(REACH_MIN ** 2 - dz ** 2, 0.0))  # the horizontal distance needed
    flat = tgt[:, :2] - shoulder[:, :2]
    r = np.linalg.norm(flat, axis=-1)
    out = flat / np.maximum(r, 1e-9)[:, None] * np.maximum(need - r, 0.0)[:, None]
    return tgt + np.c_[out, np.zeros(len(ids))]

  def _shared(self, k: int) -> bool:
    """Atom k puts its object on a surface region (On) that another atom of the goal also fills:
    the objects need spots of their own. Any other region is aimed at its centre (a spot beside
    what stands in a small region lands the object on its edge)."""
    t = self.tasks[k]
    return t.site >= 0 and t.atom.test == "on_region" and any(
        isinstance(u, Task) and u.site == t.site and u.body != t.body for j, u in enumerate(self.tasks) if j != k)

  def _spot(self, k: int, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """[n, 2] where in its region (- the region's centre) an object is placed: the point of a grid
    over the region (its body kept SPOT_MARGIN inside) with the most room (up to SPOT_ROOM)
    between the object's footprint and what already stands there (a moka pot on the stove).
    The region's centre is preferred, unless a later atom puts another object onto the same
    surface: then its corners (room left for the next one). In a container the centre stays
    preferred (an object lowered against a basket's wall drags the basket along)."""
    a, t = self.batch.data, self.tasks[k]
    size = np.abs(a["site_xmat"][ids, t.site].reshape(-1, 3, 3)[:, :2, :2]) @ np.asarray(t.atom.size)[:2]
    centre = (lo + hi) / 2
    body = np.abs(a["xpos"][ids, t.body, :2] - centre[:, :2])  # the test reads the body's position
    free = np.maximum(size - SPOT_MARGIN - body, 0.0)  # [n, 2]
    grid = np.linspace(-1.0, 1.0, 5)
    frac = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)  # [c, 2]
    offsets = frac[None] * free[:, None]  # [n, c, 2]
    site = a["site_xpos"][ids, t.site]
    place_top = site[:, 2] + (np.asarray(t.atom.size)[2] if t.atom.test == "on_region" else 0.0)
    gpos, gmat, half, top, bottom = self._standing(t, ids)
    height = hi[:, 2] - lo[:, 2]
    # what stands in the band the object will occupy (not the stove's burner, nor a roof above it)
    surface = place_top if t.atom.test == "on_region" else site[:, 2] - np.asarray(t.atom.size)[2]  # a box's floor
    band = (top > surface[:, None] + 0.005) & (bottom < surface[:, None] + height[:, None])
    g = np.linspace(-0.5, 0.5, 5)
    foot = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)[None] * (hi - lo)[:, None, :2]  # [n, f, 2]
    points = site[:, None, None, :2] + offsets[:, :, None] + foot[:, None]  # [n, c, f, 2]
    n, c = offsets.shape[:2]
    dist = self._flat_distance(points.reshape(n, -1, 2), gpos, gmat, half).reshape(n, c, -1, gpos.shape[1])
    room = np.where(band[:, None, None], dist, 1.0).min(axis=(2, 3))  # [n, c]
    later = t.atom.test == "on_region" and any(isinstance(u, Task) and u.site == t.site and u.body != t.body
                                               for u in self.tasks[k + 1:])
    spread = np.linalg.norm(offsets, axis=-1)
    score = np.minimum(room, SPOT_ROOM) + (0.01 if later else -0.01) * spread / max(float(free.max()), 1e-3)
    return offsets[np.arange(n), np.argmax(score, axis=1)]

  def _square(self, t: Task, ids: np.ndarray) -> np.ndarray:
    """[n] the turn (rad, about the vertical) that puts a held object's footprint square inside an
    In region's box where it does not fit as it hangs (a book into a caddy's 5.5 cm slot), or 0:
    of the quarter turns that fit, the least."""
    if t.atom.test != "in_region":
      return np.zeros(len(ids))
    a = self.batch.data
    mat = a["xmat"][ids, t.body].reshape(-1, 3, 3)
    site = a["site_xmat"][ids, t.site].reshape(-1, 3, 3)
    # the object's x from the region's x, about the world's vertical (a region's site may point down)
    phi = np.arctan2(mat[:, 1, 0], mat[:, 0, 0]) - np.arctan2(site[:, 1, 0], site[:, 0, 0])
    half = (t.box[1, :2] - t.box[0, :2]) / 2
    room = np.asarray(t.atom.size)[:2] - FIT_MARGIN

    def fits(angle):
      c, s = np.abs(np.cos(angle)), np.abs(np.sin(angle))
      return (c * half[0] + s * half[1] <= room[0]) & (s * half[0] + c * half[1] <= room[1])

    best = np.zeros(len(ids))
    cost = np.full(len(ids), np.inf)
    for quarter in range(4):
      delta = (quarter * np.pi / 2 - phi + np.pi) % (2 * np.pi) - np.pi
      better = fits(phi + delta) & (np.abs(delta) < cost)
      best, cost = np.where(better, delta, best), np.where(better, np.abs(delta), cost)
    return np.where(fits(phi), 0.0, best)

  def _lean(self, t: Task, ids: np.ndarray) -> np.ndarray:
    """[n, 2] the horizontal way a held object's top tips for its set-down (unit), or 0: only in an
    In region that it would fail standing upright on the container's floor (its body under the
    region's box); toward the lower of the walls across the region's narrow side (the caddy's
    divider), the top resting on it."""
    if t.atom.test != "in_region":
      return np.zeros((len(ids), 2))
    a = self.batch.data
    site, mat = a["site_xpos"][ids, t.site], a["site_xmat"][ids, t.site].reshape(-1, 3, 3)
    half = np.abs(np.einsum("bij,j->bi", mat, np.asarray(t.atom.size)))
    bottom = site[:, 2] - half[:, 2] - t.atom.in_box_below
    gpos, gmat, ghalf, top, _ = self._standing(t, ids)
    under = self._flat_distance(site[:, None, :2], gpos, gmat, ghalf)[:, 0] < 1e-6  # [n, g]
    floor = np.where(under & (top < site[:, 2, None]), top, -np.inf).max(-1)
    low = np.isfinite(floor) & (floor - t.box[0, 2] < bottom + LEAN_BELOW)  # its body, standing on the floor
    narrow = np.where((half[:, 0] < half[:, 1])[:, None], [1.0, 0.0], [0.0, 1.0])  # world axes
    probe = site[:, None, :2] + np.array([1.0, -1.0])[None, :, None] * narrow[:, None] * (
        (half[:, :2] * narrow).sum(-1)[:, None, None] + WALL_PROBE)
    near = self._flat_distance(probe, gpos, gmat, ghalf) < WALL_PROBE / 2  # [n, 2, g]
    wall = np.where(near, top[:, None], -np.inf).max(-1)  # [n, 2]: the walls' tops beyond either side
    way = np.where((wall[:, 0] <= wall[:, 1])[:, None], narrow, -narrow)
    return np.where((low & np.isfinite(wall).all(-1))[:, None], way, 0.0)

  # ---------------------------------------------------------------- one control step

  def act(self) -> np.ndarray:
    """LIBERO actions [B, 7] for the batch's current state; advances the state machines."""
    n = self.batch.num_envs
    hand, hand_mat = self._hand()
    q = self.batch.data["qpos"]
    gap = np.abs(q[:, self._finger_q[0]] - q[:, self._finger_q[1]])
    closing, self.gap = np.abs(gap - self.gap), gap
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
      grasp_z = hi[:, 2] - (np.minimum(GRASP_DEPTH, height / 2) if t.rim is None else RIM_DEPTH)
      start = self.fresh[ids] & (phase == ABOVE)
      if start.any():
        sel = ids[start]
        rest = self.from_articulated[sel]
        ref = np.where(rest[:, None, None], self.articulated.down, hand_mat[sel])
        self.goal_ori[sel], self.grasp_xy[sel], self.opening[sel] = self._grasp_plan(
            t, sel, ref, centre[start], grasp_z[start], rest)
        self.traverse[sel] = ~rest
        self.from_articulated[sel] = False
        self.spot[sel] = self._spot(k, sel, lo[start], hi[start]) if self._shared(k) else 0.0
        place_xy[start] = self._target(t, sel)[0]
      grasp_xy = centre[:, :2] + self.grasp_xy[ids]
      carry_z = self.carry_z[ids]
      tgt = hand[ids].copy()
      g = np.full(ids.size, -1.0)
      sel = (phase == ABOVE) | (phase == DESCEND)  # opened as far as the plan has room for
      width = self.opening[ids[sel]]
      g[sel] = np.where(gap[ids[sel]] > width + OPENING_TOLERANCE, 1.0,
                        np.where(gap[ids[sel]] < width - OPENING_TOLERANCE, -1.0, 0.0))
      sel = phase == ABOVE
      tgt[sel] = np.c_[grasp_xy[sel], hi[sel, 2] + CLEARANCE]
      far = sel & self.traverse[ids] & (np.linalg.norm(grasp_xy - hand[ids, :2], axis=-1) > TRAVERSE_NEAR)
      if far.any():  # over what stands on the way, then down
        tgt[far, 2] = np.maximum(tgt[far, 2], self._path_top(t, ids[far], hand[ids[far], :2], grasp_xy[far])
                                 + TRAVERSE_CLEARANCE)
      sel = phase == DESCEND
      tgt[sel] = np.c_[grasp_xy[sel], grasp_z[sel]]
      sel = phase == CLOSE
      g[sel] = 1.0
      tgt[sel] = np.c_[grasp_xy[sel], grasp_z[sel]]
      sel = phase == LIFT
      g[sel] = 1.0
      tgt[sel, 2] = carry_z[sel]
      slide = sel & (np.linalg.norm(self.lift_xy[ids] - hand[ids, :2], axis=-1) > 0.01) & (
          self.count[ids] < self.slide_steps[ids])
      tgt[slide] = np.c_[self.lift_xy[ids[slide]], self.lift_z[ids[slide]] + SLIDE_RAISE]
      rise = sel & ~slide
      if t.rim is None:  # not a rim grasp: slid by its 3 mm wall, a bowl on LIBERO-Spatial 7's stove slipped out
        tgt[rise] = self._reach_out(ids[rise], tgt[rise], carry_z[rise])
      sel = phase == CARRY
      g[sel] = 1.0
      tgt[sel] = np.c_[place_xy[sel] - self.offset[ids[sel], :2], carry_z[sel]]
      if t.rim is not None:  # held by a wall 3 mm thick: no jerks
        step = tgt[sel] - hand[ids[sel]]
        tgt[sel] = hand[ids[sel]] + step * np.minimum(1.0, RIM_CARRY_STEP / np.maximum(
            np.linalg.norm(step, axis=-1, keepdims=True), 1e-9))
      sel = phase == LOWER
      g[sel] = 1.0
      below = hand[ids[sel], 2] - lo[sel, 2]  # the hand's height over the object's bottom
      if t.atom.test == "in_region":
        z = place_top[sel] + (hand[ids[sel], 2] - centre[sel, 2])
      elif t.rim is not None and t.target_body >= 0 and sel.any():  # released low over the dish's floor
        z = self._floor(t, ids[sel], place_xy[sel], place_top[sel]) + RIM_RELEASE_ABOVE + below
      else:
        z = place_top[sel] + RELEASE_ABOVE + below
      aim = centre[sel, :2] if t.rim is None else self.batch.data["xpos"][ids[sel], t.body, :2]  # a bowl's base
      leaned = self.lean[ids[sel]].any(-1)
      if leaned.any():  # a tipped object's foot (its bottom's centre) over the region's centre
        a = self.batch.data
        foot = np.r_[(t.box[0, :2] + t.box[1, :2]) / 2, t.box[0, 2]]
        feet = a["xpos"][ids[sel], t.body] + a["xmat"][ids[sel], t.body].reshape(-1, 3, 3) @ foot
        aim = np.where(leaned[:, None], feet[:, :2], aim)
      tgt[sel] = np.c_[place_xy[sel] - (aim - hand[ids[sel], :2]), z]  # where it hangs now
      sel = phase == RELEASE
      tgt[sel] = hand[ids[sel]]
      sel = (phase == RETREAT) | (phase == DONE)
      tgt[sel, 2] = place_top[sel] + LIFT_CLEARANCE + height[sel]
      target[ids], grip[ids] = tgt, g

      err = np.linalg.norm(tgt - hand[ids], axis=-1)
      count = self.count[ids] + 1
      done = np.zeros(ids.size, bool)
      flat = np.linalg.norm(tgt[:, :2] - hand[ids, :2], axis=-1)
      turned = np.linalg.norm(_rotation_error(self.goal_ori[ids], hand_mat[ids]), axis=-1) < ABOVE_TURNED
      done |= (phase == ABOVE) & (flat < 0.01) & (np.abs(tgt[:, 2] - hand[ids, 2]) < ABOVE_Z_TOLERANCE) & turned
      done |= (phase == DESCEND) & (err < 0.006)
      done |= (phase == CLOSE) & (count >= CLOSE_STEPS) & ((closing[ids] < CLOSED_SPEED) | (count >= CLOSE_STEPS_MAX))
      done |= (phase == LIFT) & (np.abs(carry_z - hand[ids, 2]) < 0.02)
      done |= (phase == CARRY) & (np.linalg.norm(tgt[:, :2] - hand[ids, :2], axis=-1) < 0.01) & (
          ~self.turned[ids] | (np.linalg.norm(_rotation_error(self.goal_ori[ids], hand_mat[ids]), axis=-1) < CARRY_TURNED))
      # or resting on something: the hand held still over the target (an In region's middle may lie
      # below its container's floor: a drawer's)
      still = np.abs(hand[ids, 2] - self.hand_z[ids]) < STILL_SPEED
      self.still[ids] = np.where((phase == LOWER) & still, self.still[ids] + 1, 0)
      done |= (phase == LOWER) & ((err < 0.008) | (self.still[ids] >= STILL_STEPS))
      done |= (phase == RELEASE) & (count >= RELEASE_STEPS)
      done |= (phase == RETREAT) & (err < 0.02)
      done |= (phase < DONE) & (count >= PHASE_LIMIT) & (phase != CLOSE) & (phase != RELEASE)
      closed = done & (phase == CLOSE)  # the object still where it lay: the height to carry it at
      self.carry_z[ids[closed]] = (np.maximum(hi[closed, 2], place_top[closed]) + LIFT_CLEARANCE
                                   + (hand[ids[closed], 2] - lo[closed, 2]))
      if closed.any():
        got = ids[closed]
        self.lift_xy[got] = hand[got, :2] + self._escape(t, got, lo[closed], hi[closed])
        self.lift_z[got] = hand[got, 2]
        out = self.lift_xy[got] if t.rim is not None else self._reach_out(
            got, np.c_[self.lift_xy[got], self.lift_z[got]], self.carry_z[got])[:, :2]
        moved = np.linalg.norm(out - self.lift_xy[got], axis=-1) > 0.0
        self.slide_steps[got] = np.where(moved, REACH_SLIDE_STEPS, SLIDE_STEPS)
        self.lift_xy[got] = out
      lifted = done & (phase == LIFT)
      self.offset[ids[lifted]] = centre[lifted] - hand[ids[lifted]]
      if lifted.any():  # turned with the hand while carried: square to a region it fits only so
        turn = self._square(t, ids[lifted])
        rz = _yaw_matrix(turn)
        self.goal_ori[ids[lifted]] = rz @ self.goal_ori[ids[lifted]]
        self.offset[ids[lifted]] = np.einsum("bij,bj->bi", rz, self.offset[ids[lifted]])
        way = self._lean(t, ids[lifted])
        self.lean[ids[lifted]] = way
        leaned = way.any(-1)  # the fingers tip toward the higher wall: the object's top toward the lower
        axis = np.cross([0.0, 0.0, 1.0], np.c_[way, np.zeros(len(way))])
        self.goal_ori[ids[lifted]] = articulated._rodrigues(
            np.where(leaned[:, None], axis, [1.0, 0.0, 0.0]), np.where(leaned, LEAN_TILT, 0.0)) @ self.goal_ori[ids[lifted]]
        self.turned[ids[lifted]] = (turn != 0.0) | leaned
      nxt = np.where(done, phase + 1, phase)
      # a grasp across the object that closed on nothing (the fingers landed on a neighbour's edge)
      # starts over from above (not a rim grasp: a bowl's 3 mm wall leaves the fingers as close)
      missed = (phase == LIFT) & (count > 3) & (gap[ids] < EMPTY_GAP) & (t.rim is None)
      done |= missed
      nxt = np.where(missed, ABOVE, nxt)
      last = nxt == DONE
      more = last & (k + 1 < len(self.tasks))  # next atom
      self.task[ids[more]] = k + 1
      nxt = np.where(more, ABOVE, nxt)
      self.phase[ids] = nxt
      self.count[ids] = np.where(done, 0, count)
      self.fresh[ids] = done
    self.hand_z = hand[:, 2].copy()
    self.articulated.act(hand, hand_mat, target, grip)
    self.laydown.act(hand, hand_mat, target, grip)
    pos = np.clip((target - hand) / 0.05, -1, 1)
    rot = np.clip(_rotation_error(self.goal_ori, hand_mat) / 0.5, -1, 1)
    return np.concatenate([pos, rot, grip[:, None]], axis=1)


def _yaw_matrix(angle: np.ndarray) -> np.ndarray:
  """[n, 3, 3] rotations by `angle` [n] (rad) about the vertical."""
  c, s = np.cos(angle), np.sin(angle)
  rz = np.zeros((len(angle), 3, 3))
  rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
  return rz


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

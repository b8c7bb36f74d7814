"""Scripted articulated steps for LIBERO's experts, and the goal's plan (the order of its steps).

`plan` turns a goal into ordered steps: the stove's switches first (nothing placed yet stands in
the hand's way), then every drawer or door a placement needs open (a prerequisite the goal does
not list, added when some env starts with it shut) and the goal's own Open atoms, then the
placements, then the Close atoms (a container is shut only once its contents are in). Which
steps are ours is read from the atoms and the scene: joint atoms, and On(region) of an object too
wide and flat to grasp across (a plate), which is dragged, and In(region behind a hinged door) of
an object with a handle (a mug into a microwave), which is inserted. Other placements stay with
`expert.Expert`.

`Articulated` drives the envs whose current step is one of ours, batched over those envs, from
privileged state (the joints' axes, anchors and positions; the moving bodies' geoms):
- a drawer (a slide joint) to open is grasped by its handle, the geom that sticks out furthest
  along the opening direction, with the hand turned to point into the drawer and the fingers
  closing across the bar vertically, then pulled along the joint's axis; a drawer to shut is
  pushed by its handle, the fingers tilted toward the push (the forearm clear of the cabinet);
- a hinge without a handle we grasp (a door) is pushed on its panel's outer face near the top,
  the fingertips leading the door's face along its arc and the hand turning with the door;
- a switch (the stove's knob) is grasped across its raised part and twisted about its axis;
- a mug into a microwave (In a region behind a hinged door, of an object with a handle) is taken
  by its handle with the hand pointing in through the opening, tipped down, lifted over the floor's
  edge and pushed in, the hand kept outside (a downward hand over it meets the microwave's ceiling);
- an object too wide and flat to grasp across (a plate) is dragged over the table by its rim,
  pinched on the side toward the region (the plate's far side may be against a cabinet), the
  hand's goal re-aimed every step from the object's centre to a spot past the region's centre
  (`DRAG_DEEP`), and the drag stops once the object is well inside the region or at that spot.
Each step ends with the gripper open, the hand backed off and turned back to the reset pose's
downward orientation (what the pick-and-place expert starts from); a joint step whose atom
still fails then is tried again.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from envs.libero import predicates

PLACE, PULL, PUSH_JOINT, TWIST, DRAG, INSERT = "place", "pull", "push_joint", "twist", "drag", "insert"
PRE, IN, GRIP, DRIVE, RELEASE, BACK, RESTORE, DONE = range(8)
PHASES = ("pre", "in", "grip", "drive", "release", "back", "restore", "done")
# Joint goals: drive past the predicate's threshold by this share of the rest of the joint's range
# (at most JOINT_MARGIN_MAX), so the atom still holds after the hand lets go.
JOINT_MARGIN, JOINT_MARGIN_MAX = 0.5, 0.3
SLIDE_LEAD = 0.04  # m: the handle's goal runs this far ahead of the drawer while driving it ...
SLIDE_PAST = 0.01  # m: ... toward this far past the joint's goal
HANDLE_OPENING = 0.026  # m: each finger's opening (its joint) when reaching for a handle bar
FINGER_DEADBAND = 0.004  # m
HINGE_LEAD = 0.2  # rad: a pushed door's goal runs this far ahead of it
TWIST_LEAD, TWIST_PAST = 0.4, 0.15  # rad: a twisted knob's goal runs this far ahead, toward this far past its goal
PRE_BACK = 0.05  # m in front of a handle (or behind a pushed face) before moving in
PUSH_TILT = 0.6  # rad: a drawer is pushed shut with the fingers tilted this far toward the push
PUSH_BACK = 0.02  # m: the pusher waits this far off the face before pushing
BACK_OFF = 0.08  # m the hand backs away after letting go
SAFE_UP = 0.08  # m above the moving part's top while moving to or from it
PAD_IN = 0.004  # m: the finger pads' centre sits this far behind the grip site (toward the palm)
FINGER_HALF = 0.011  # m: half a Panda finger's width across its closing axis
PALM_ABOVE = 0.026  # m: the palm's bottom over the grip site; FINGERTIP below it
FINGERTIP = 0.012
PALM_CLEAR = 0.01  # m the palm keeps above a pushed door's top
KNOB_RAISED = 0.03  # m: a knob's geoms whose tops are this close to its highest are its grip
KNOB_GRIP_DEPTH = 0.015  # m below the knob's top
PINCH_RADIUS = 0.058  # m from a dragged dish's centre: where its rim is pinched (LIBERO's plate: 3.0-6.7 cm)
PINCH_HEIGHT = 0.014  # m: the grip site over the dish's bottom (its rim there ~1.1 cm up; fingertips 1.2 cm below the site)
DRAG_PAST, DRAG_STEP = 0.015, 0.02  # m
# m: a dragged object is aimed this far past its region's centre along its way in (kept PUSH_MARGIN
# inside): what it shoves ahead of it (LIBERO-Goal 5: the cream cheese just short of the region)
# stays at the region's near edge, not under the object's rim at its centre
DRAG_DEEP = 0.03
FINGERS_EMPTY = 0.003  # m: the fingers' joints this close to shut hold nothing
PUSH_MARGIN = 0.01  # m: a pushed object inside its region by this much counts as there
PUSH_DONE = 0.025  # m: a push stops with the object's centre this close to its aim (`DRAG_DEEP`)
DRAG_MIN_WIDTH = 0.07  # m: an object wider than the open fingers on both sides ...
DRAG_MAX_HEIGHT = 0.03  # m: ... and this flat is dragged by its rim, not grasped across
INTEGRAL_GAIN, INTEGRAL_NEAR, INTEGRAL_MAX = 0.15, 0.03, 0.04  # per step, m, m
SLOW_STEP, DRIVE_STEP = 0.015, 0.02  # m: the most the hand's goal leads it by while moving in or driving a joint
PRE_REACHED = 0.02  # m: the pre-pose is reached this closely
IN_REACHED = 0.01  # m: a handle's grip point is reached this closely (the fingers open 2.6 cm either side of its bar)
DRIVE_STUCK = 0.01  # m/s: a pulled drawer this slow is stuck
STALLED = 1e-3  # m/s or rad/s: a joint this slow has stopped
GRIP_STEPS, RELEASE_STEPS = 10, 8
RESTORED = 0.03  # rad: the hand this close to the reset pose's orientation hands over (a pick plans its grasp from it)
PHASE_LIMIT = 60  # control steps before a phase gives up waiting
DRIVE_LIMIT = 120
RETRIES = 2  # a joint step whose atom fails at its end starts over this many times
# Insert: a mug into a microwave. A downward hand holding it by its rim stays above it, and the
# microwave's ceiling (14 cm over its floor) stops it; the mug is taken by its handle instead (the
# geom furthest out from its rim's centre, on the side away from the opening), the hand pointing
# at the mug along the way in and tipped down (a level hand's wrist sits on the table's other mug),
# lifted over the floor's front edge and pushed in level, the hand kept outside the opening.
INSERT_PITCH = 0.7  # rad the hand points below the horizontal
INSERT_PRE = 0.1  # m before the handle (against the way in) the hand starts from
INSERT_ABOVE = 0.025  # m: the mug's bottom over the region's bottom while pushed in
INSERT_DEPTH = 0.03  # m: the mug's body this far inside the region's front face (its cup behind it, off the back wall)
INSERT_REACHED = 0.01  # m: the push ends with the body this close to its goal
INSERT_TURN = 0.3  # rad the hand heads off the way in, away from the arm
# On its way to a drawer's pre-pose the hand (turning to point into the drawer, its fingers closing
# vertically) reaches the palm's half length (10.5 cm) below its site. Moved there at the handle's
# height it swept LIBERO-Goal 0's bowl along in front of the cabinet, where the middle drawer stopped
# against it at -0.04 m (the threshold is -0.14); it keeps its height over what stands on its way,
# then descends.
PRE_CLEARANCE = 0.03  # m between the hand's lowest reach and the tops it passes over
PRE_NEAR = 0.03  # m: this close (horizontally) to the pre-pose the hand descends to it


@dataclasses.dataclass(frozen=True)
class Step:
  """One articulated step resolved to ids: the atom it makes true and how."""
  kind: str
  atom: predicates.Atom
  joint: int = -1  # the joint driven
  body: int = -1  # the joint's (moving) body
  sign: float = 1.0  # +1 if the atom needs q to rise
  goal_q: float = 0.0  # where the joint is driven
  part: int = -1  # pull: the handle geom; push_joint: the door panel geom
  grip_local: np.ndarray | None = None  # twist: the grip point in the knob's body frame
  across: np.ndarray | None = None  # twist: the knob's thin horizontal side, body frame (unit)
  box: np.ndarray | None = None  # drag, insert: the object's box in its body frame
  site: int = -1  # drag, insert: the region's site
  way: np.ndarray | None = None  # insert: the world's horizontal way in (unit), into the container's opening


def _joint_atom(scene, model, predicate: str, name: str) -> predicates.Atom:
  """An Open/Close atom of a region or object that the goal does not state (a prerequisite),
  compiled as predicates.compile_goal compiles the goal's."""
  objects, regions = scene.meta["objects"], scene.meta["regions"]
  if name in regions:
    joints, owner = regions[name]["joints"] or [j["name"] for j in objects[regions[name]["parent"]]["joints"]], \
        regions[name]["parent"]
  else:
    joints, owner = [j["name"] for j in objects[name]["joints"]], name
  compare, ranges, end = predicates._JOINT_RULES[predicate, objects[owner]["class"]]
  adr = tuple(int(model.jnt_qposadr[model.joint(j).id]) for j in joints)
  return predicates.Atom(predicate, (name,), "joints", qposadr=adr, compare=compare,
                         threshold=float(end(objects[owner]["articulation"][ranges])),
                         quantifier=predicates._QUANTIFIER[predicate])


def _container(scene, atom: predicates.Atom) -> str | None:
  """The articulated object a placement goes into (In a region of a fixture with joints), else None."""
  regions, objects = scene.meta["regions"], scene.meta["objects"]
  if atom.test != "in_region":
    return None
  region = regions[atom.args[1]]
  parent = region["parent"]
  if parent is None or not objects[parent]["joints"] or ("open", objects[parent]["class"]) not in predicates._JOINT_RULES:
    return None
  return atom.args[1] if region["joints"] else parent


def _dragged(model, atom: predicates.Atom) -> bool:
  """On(region) of an object wider than the open fingers both ways and flat: dragged, not grasped."""
  if atom.test != "on_region":
    return False
  from envs.libero.expert import _box
  extent = np.diff(_box(model, atom.body), axis=0)[0]
  return bool(extent[:2].min() > DRAG_MIN_WIDTH and extent[2] < DRAG_MAX_HEIGHT)


def _handle(model, body: int) -> np.ndarray | None:
  """The body-frame centre of an object's handle: of its colliding geoms the one furthest (horizontally)
  from the centre of the geoms reaching its top (a mug's rim), if that is well outside the rim."""
  from envs.libero.expert import _box, _rim
  rim = _rim(model, body, _box(model, body))
  if rim is None:
    return None
  middle = rim.mean(0)
  geoms = _colliding(model, body)
  centres = np.array([_geom_box(model, g)[0] for g in geoms])
  reach = np.linalg.norm((centres - middle)[:, :2], axis=-1)
  radius = np.linalg.norm((rim - middle)[:, :2], axis=-1).max()
  return centres[int(np.argmax(reach))] if reach.max() > radius + FINGER_HALF else None


def _inserted(scene, model, atom: predicates.Atom) -> bool:
  """In a region of a fixture behind a hinged door (a microwave), of an object with a handle."""
  name = _container(scene, atom)
  if name is None:
    return False
  joint = _joint_of(model, _joint_atom(scene, model, "open", name))
  return int(model.jnt_type[joint]) == int(mujoco.mjtJoint.mjJNT_HINGE) and _handle(model, atom.body) is not None


def plan(batch) -> list[tuple[str, predicates.Atom]]:
  """The goal's steps in the order the expert does them, as (kind, atom); kind PLACE goes to the
  pick-and-place expert. Computed from the goal and every env's current state (prerequisite
  Opens are added only if some env needs them)."""
  scene, model = batch.scene, batch.model
  qpos = batch.data["qpos"]
  switches, opens, places, closes, other = [], [], [], [], []
  for atom in batch.goal.atoms:
    if atom.test == "joints" and atom.predicate in ("turnon", "turnoff"):
      switches.append(atom)
    elif atom.test == "joints" and atom.predicate == "open":
      opens.append(atom)
    elif atom.test == "joints":
      closes.append(atom)
    elif atom.test in ("in_region", "on_region", "on_object"):
      places.append(atom)
    else:
      other.append(atom)
  for atom in places:
    name = _container(scene, atom)
    if name is None or any(a.args[0] == name for a in opens):
      continue
    need = _joint_atom(scene, model, "open", name)
    shut = ~predicates._joints(need, predicates.GoalInputs(None, None, None, None, qpos, None))
    if shut.any():
      opens.append(need)
  steps = [(_joint_kind(scene, model, a), a) for a in switches + opens]
  from envs.libero import laydown  # a tall object onto a tilted board is laid down (envs.libero.laydown)
  steps += [(DRAG if _dragged(model, a) else INSERT if _inserted(scene, model, a)
             else laydown.LAY if laydown.applies(model, scene, a) else PLACE, a) for a in places]
  steps += [(_joint_kind(scene, model, a), a) for a in closes]
  return steps + [(PLACE, a) for a in other]  # the pick-and-place expert names what it cannot do


def _joint_kind(scene, model, atom: predicates.Atom) -> str:
  if atom.predicate in ("turnon", "turnoff"):
    return TWIST
  jid = _joint_of(model, atom)
  slide = int(model.jnt_type[jid]) == int(mujoco.mjtJoint.mjJNT_SLIDE)
  return PULL if slide and atom.predicate == "open" else PUSH_JOINT  # a drawer is shut by pushing its handle


def _joint_of(model, atom: predicates.Atom) -> int:
  """The joint a step drives: the atom's first (LIBERO's regions name one; a stove has one knob)."""
  return int(np.flatnonzero(model.jnt_qposadr == atom.qposadr[0])[0])


def _geom_box(model, g: int) -> tuple[np.ndarray, np.ndarray]:
  """(centre, half extents) of a geom's box in its body's frame."""
  rot = np.zeros(9)
  mujoco.mju_quat2Mat(rot, model.geom_quat[g])
  rot = rot.reshape(3, 3)
  centre = model.geom_pos[g] + rot @ model.geom_aabb[g, :3]
  return centre, np.abs(rot) @ model.geom_aabb[g, 3:]


def _colliding(model, body: int) -> list[int]:
  return [g for g in range(model.ngeom) if model.geom_bodyid[g] == body
          and (model.geom_contype[g] or model.geom_conaffinity[g])]


def make_step(batch, kind: str, atom: predicates.Atom) -> Step:
  """Resolve a planned step to ids and geometry of the model (task constants)."""
  model = batch.model
  if kind == DRAG:
    from envs.libero.expert import _box
    return Step(kind, atom, box=_box(model, atom.body), site=atom.site)
  if kind == INSERT:  # the handle, and the way in through the opening (the side no wall covers)
    from envs.libero.expert import _box
    return Step(kind, atom, box=_box(model, atom.body), site=atom.site, grip_local=_handle(model, atom.body),
                way=_way_in(batch, atom))
  jid = _joint_of(model, atom)
  body = int(model.jnt_bodyid[jid])
  lo, hi = model.jnt_range[jid]
  thr = atom.threshold
  sign = 1.0 if atom.compare in (">", ">=") else -1.0
  rest = (hi - thr) if sign > 0 else (thr - lo)
  goal_q = thr + sign * min(JOINT_MARGIN * rest, JOINT_MARGIN_MAX)
  axis = model.jnt_axis[jid]
  geoms = _colliding(model, body)
  slide = int(model.jnt_type[jid]) == int(mujoco.mjtJoint.mjJNT_SLIDE)
  if kind == PULL or (kind == PUSH_JOINT and slide):  # the handle: the geom furthest along the opening direction
    opening = sign * axis if atom.predicate == "open" else -sign * axis
    reach = [_geom_box(model, g)[0] @ opening + _geom_box(model, g)[1] @ np.abs(opening) for g in geoms]
    return Step(kind, atom, joint=jid, body=body, sign=sign, goal_q=goal_q, part=geoms[int(np.argmax(reach))])
  if kind == PUSH_JOINT:  # the door's panel: its largest geom
    volume = [np.prod(_geom_box(model, g)[1] + 1e-4) for g in geoms]
    return Step(kind, atom, joint=jid, body=body, sign=sign, goal_q=goal_q, part=geoms[int(np.argmax(volume))])
  boxes = [_geom_box(model, g) for g in geoms]  # TWIST: the knob's raised geoms are its grip
  tops = np.array([c[2] + h[2] for c, h in boxes])
  raised = [b for b, t in zip(boxes, tops) if t > tops.max() - KNOB_RAISED]
  lo_r = np.min([c - h for c, h in raised], axis=0)
  hi_r = np.max([c + h for c, h in raised], axis=0)
  across = np.eye(3)[int(np.argmin((hi_r - lo_r)[:2]))]
  grip = (lo_r + hi_r) / 2
  grip[2] = hi_r[2] - KNOB_GRIP_DEPTH
  return Step(kind, atom, joint=jid, body=body, sign=sign, goal_q=goal_q, grip_local=grip, across=across)


def _way_in(batch, atom: predicates.Atom) -> np.ndarray:
  """[2] the world's horizontal way into a region through its container's opening: of the region's
  four sides, the one no colliding geom of the container (its walls, not its door) stands in front of."""
  model, a = batch.model, batch.data
  parent = batch.scene.meta["regions"][atom.args[1]]["parent"]
  root = model.body(batch.scene.meta["objects"][parent]["body"]).id
  site, mat = a["site_xpos"][0, atom.site], a["site_xmat"][0, atom.site].reshape(3, 3)
  half = np.abs(mat @ np.asarray(atom.size))
  best, score = None, np.inf
  for u in ([1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]):
    u = np.asarray(u)
    probe = site[:2] + u * (np.abs(u) @ half[:2] + 0.02)  # just outside that side, at the region's middle height
    cover = 0.0
    for g in _colliding(model, root):
      if model.geom_bodyid[g] != root:  # the fixture's own walls (not its door)
        continue
      c, h = _geom_box(model, g)
      r = a["xmat"][0, root].reshape(3, 3)
      centre, ext = a["xpos"][0, root] + r @ c, np.abs(r) @ h
      inside = np.all(np.abs(np.r_[probe, site[2]] - centre) <= ext + 0.005)
      cover += float(inside)
    if cover < score:
      best, score = -u, cover
  return best


def _rodrigues(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
  """[n, 3, 3] rotations by `angle` [n] about unit `axis` [n, 3]."""
  k = np.zeros((len(angle), 3, 3))
  k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
  k = k - np.swapaxes(k, 1, 2)
  s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
  return np.eye(3) + s * k + (1 - c) * (k @ k)


def _yaw(angle: np.ndarray) -> np.ndarray:
  return _rodrigues(np.tile([0.0, 0.0, 1.0], (len(angle), 1)), angle)


def _yaw_to(down: np.ndarray, direction: np.ndarray, hand: np.ndarray | None = None) -> np.ndarray:
  """[n] a turn about the vertical that puts the downward hand's closing axis (its site x) along
  ±`direction` [n, 2] (the fingers are symmetric): of the two, the one nearer the hand's
  orientation `hand` [n, 3, 3] (else the least)."""
  x = down[:, :2, 0]
  angle = np.arctan2(x[:, 0] * direction[:, 1] - x[:, 1] * direction[:, 0], (x * direction).sum(-1))
  angle = (angle + np.pi / 2) % np.pi - np.pi / 2
  if hand is None:
    return angle
  other = angle - np.sign(angle + 1e-12) * np.pi
  err = [np.linalg.norm(_rotation_error(_yaw(a) @ down, hand), axis=-1) for a in (angle, other)]
  return np.where(err[1] < err[0], other, angle)


def _unit(v: np.ndarray) -> np.ndarray:
  return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


class Articulated:
  """The articulated steps of an `expert.Expert`'s plan, for the envs whose current step is one."""

  def __init__(self, expert, steps: dict[int, Step]):
    self.expert, self.batch, self.steps = expert, expert.batch, steps  # plan index -> Step
    n = self.batch.num_envs
    self.down = np.asarray(self.batch.params.initial_goal_ori, float)  # the reset pose's hand
    self.entered = np.full(n, -1)  # the plan step each env's state below belongs to
    self.phase = np.zeros(n, np.int64)
    self.count = np.zeros(n, np.int64)
    self.retries = np.zeros(n, np.int64)
    self.ori = np.zeros((n, 3, 3))  # the hand's orientation through the step (at the grip, for a twist)
    self.q0 = np.zeros(n)  # the joint where the hand took hold of it (twist, door)
    self.grip_pos = np.zeros((n, 3))  # twist: the grip site's position at the grasp
    self.away = np.zeros((n, 3))  # the unit direction the hand backs off along
    self._fingers = [j["qposadr"] for j in self.batch.scene.meta["robot"]["gripper_joints"]]
    self.integral = np.zeros((n, 3))  # the position error integrated near a phase's goal
    self.back_from = np.zeros((n, 3))  # where the hand backs off to, then rises from
    self.drag_spot = np.zeros((n, 2))  # drag: where in its region the object is aimed - the region's centre
    owners = set(expert._obstacles["owner"].tolist())
    self.owner = {}  # plan index -> the object (of the expert's obstacles) a step's joint belongs to
    for k, step in steps.items():
      b = step.body
      while b > 0 and b not in owners:
        b = int(self.batch.model.body_parentid[b])
      self.owner[k] = b

  def _inside(self, step: Step, ids: np.ndarray) -> np.ndarray:
    """The dragged object's atom holds with PUSH_MARGIN to spare on every side of its region."""
    size = tuple(np.asarray(step.atom.size) - [PUSH_MARGIN, PUSH_MARGIN, 0.0])
    inputs = predicates.GoalInputs(*[f[ids] for f in self.batch.goal_inputs()])
    return predicates._TESTS[step.atom.test](dataclasses.replace(step.atom, size=size), inputs)

  def _drag_goal(self, step: Step, ids: np.ndarray) -> np.ndarray:
    """[n, 2] where a dragged object's centre is aimed: its region's centre + `drag_spot`."""
    return self.batch.data["site_xpos"][ids, step.site, :2] + self.drag_spot[ids]

  def _holds(self, step: Step, ids: np.ndarray) -> np.ndarray:
    a = self.batch.data
    if step.kind == INSERT:
      return predicates._TESTS[step.atom.test](step.atom, predicates.GoalInputs(*[f[ids] for f in self.batch.goal_inputs()]))
    if step.kind == DRAG:  # in the region's middle half, or the atom itself holds (a plate dragged
      # to the region's edge is there: dragging it again would cost the rest of the episode)
      d = a["site_xpos"][ids, step.site, :2] - a["xpos"][ids, step.atom.body, :2]
      inputs = predicates.GoalInputs(*[f[ids] for f in self.batch.goal_inputs()])
      return (np.linalg.norm(d, axis=-1) < min(step.atom.size[:2]) - PUSH_MARGIN) | \
          predicates._TESTS[step.atom.test](step.atom, inputs)
    return predicates._joints(step.atom, predicates.GoalInputs(None, None, None, None, a["qpos"][ids], None))

  def _preset(self, ids: np.ndarray, opening: float) -> np.ndarray:
    """Gripper actions that bring each finger's joint to `opening` (the command integrates its
    sign; 0 holds it)."""
    q = np.abs(self.batch.data["qpos"][ids][:, self._fingers]).mean(-1)
    return np.where(q > opening + FINGER_DEADBAND, 1.0, np.where(q < opening - FINGER_DEADBAND, -1.0, 0.0))

  def _reached(self, step: Step, ids: np.ndarray) -> np.ndarray:
    """The joint is at its goal (past the threshold by the step's margin)."""
    if step.kind == DRAG:
      d = self._drag_goal(step, ids) - self.batch.data["xpos"][ids, step.atom.body, :2]
      return (np.linalg.norm(d, axis=-1) < PUSH_DONE) | self._inside(step, ids)
    if step.kind == INSERT:
      d = self._insert_goal(step, ids) - self.batch.data["xpos"][ids, step.atom.body, :2]
      return np.linalg.norm(d, axis=-1) < INSERT_REACHED
    q = self.batch.data["qpos"][ids, self.batch.model.jnt_qposadr[step.joint]]
    dq = self.batch.data["qvel"][ids, self.batch.model.jnt_dofadr[step.joint]]
    # or past the atom's threshold and stopped there (a drawer shut against its cabinet short of its limit)
    return (step.sign * (q - step.goal_q) >= 0) | (self._holds(step, ids) & (np.abs(dq) < STALLED))

  def _enter(self, k: int, step: Step, ids: np.ndarray, hand_mat: np.ndarray) -> None:
    a, model = self.batch.data, self.batch.model
    self.entered[ids], self.count[ids] = k, 0
    self.phase[ids] = np.where(self._holds(step, ids), DONE, PRE)
    self.q0[ids] = a["qpos"][ids, model.jnt_qposadr[step.joint]] if step.joint >= 0 else 0.0
    down = np.broadcast_to(self.down, (len(ids), 3, 3))
    if step.kind == PULL:  # point into the drawer (site z against the opening), fingers across the bar (vertical)
      opening = self._opening(step, ids)
      z = -opening
      best = None
      for s in (-1.0, 1.0):
        x = np.tile([0.0, 0.0, s], (len(ids), 1))
        r = np.stack([x, np.cross(z, x), z], axis=-1)
        score = np.trace(r @ np.swapaxes(down, 1, 2), axis1=1, axis2=2)
        best = (r, score) if best is None else (np.where((score > best[1])[:, None, None], r, best[0]),
                                                np.maximum(score, best[1]))
      self.ori[ids], self.away[ids] = best[0], opening
    elif step.kind == PUSH_JOINT and self._slide(step):  # the downward hand, its palm's long side along the handle
      opening = self._opening(step, ids)
      level = _yaw(_yaw_to(down, np.stack([-opening[:, 1], opening[:, 0]], -1), hand_mat)) @ down
      # the fingers tilted toward the push: the forearm stays back, clear of the cabinet's top
      tilt_axis = _unit(np.cross(np.tile([0.0, 0.0, -1.0], (len(ids), 1)), -opening))
      self.ori[ids] = _rodrigues(tilt_axis, np.full(len(ids), PUSH_TILT)) @ level
      self.away[ids] = opening
    elif step.kind == PUSH_JOINT:
      radial = self._door_frame(step, ids)[1]
      self.ori[ids] = _yaw(_yaw_to(down, radial[:, :2], hand_mat)) @ down
      self.away[ids] = -self._door_frame(step, ids)[2]
    elif step.kind == TWIST:
      across = np.einsum("bij,j->bi", a["xmat"][ids, step.body].reshape(-1, 3, 3), step.across)
      self.ori[ids] = _yaw(_yaw_to(down, across[:, :2], hand_mat)) @ down
      self.away[ids] = [0.0, 0.0, 1.0]
    elif step.kind == INSERT:  # pointing along the way in, tipped down; the fingers close across the handle (level)
      way = np.tile(np.r_[step.way, 0.0], (len(ids), 1))
      heading = np.einsum("bij,bj->bi", _yaw(self._insert_turn(step, ids)), way)
      z = heading * np.cos(INSERT_PITCH) + np.array([0.0, 0.0, -np.sin(INSERT_PITCH)])
      best = None
      for s in (-1.0, 1.0):
        x = s * np.stack([-heading[:, 1], heading[:, 0], np.zeros(len(ids))], -1)
        r = np.stack([x, np.cross(z, x), z], axis=-1)
        score = np.trace(r @ np.swapaxes(hand_mat, 1, 2), axis1=1, axis2=2)
        best = (r, score) if best is None else (np.where((score > best[1])[:, None, None], r, best[0]),
                                                np.maximum(score, best[1]))
      self.ori[ids], self.away[ids] = best[0], -way
    else:
      room = np.asarray(step.atom.size[:2]) - PUSH_MARGIN
      self.drag_spot[ids] = np.clip(_unit(a["site_xpos"][ids, step.site, :2] - a["xpos"][ids, step.atom.body, :2])
                                    * DRAG_DEEP, -room, room)
      u = _unit(self._drag_goal(step, ids) - a["xpos"][ids, step.atom.body, :2])
      self.ori[ids] = _yaw(_yaw_to(down, u, hand_mat)) @ down  # the fingers close across the rim (radially)
      self.away[ids] = [0.0, 0.0, 1.0]

  def _insert_turn(self, step: Step, ids: np.ndarray) -> np.ndarray:
    """[n] the hand's heading off the way in (rad, about the vertical): INSERT_TURN away from the arm,
    the hand's back turned toward the shoulder (straight along the way in, the wrist meets the other mug, or the
    arm its joint limits)."""
    a = self.batch.data
    mat = a["xmat"][ids, step.atom.body].reshape(-1, 3, 3)
    handle = a["xpos"][ids, step.atom.body] + np.einsum("bij,j->bi", mat, step.grip_local)
    arm = a["xpos"][ids, self.expert._shoulder, :2] - handle[:, :2]
    cross = step.way[0] * arm[:, 1] - step.way[1] * arm[:, 0]  # > 0: the shoulder to the way's left
    return np.where(cross > 0, -INSERT_TURN, INSERT_TURN)  # the heading away from it, its back toward it

  def _insert_goal(self, step: Step, ids: np.ndarray) -> np.ndarray:
    """[n, 2] where an inserted object's body goes: INSERT_DEPTH inside the region's face toward the
    opening, level with the region's centre across the way in."""
    a = self.batch.data
    half = np.abs(a["site_xmat"][ids, step.site].reshape(-1, 3, 3) @ np.asarray(step.atom.size))
    depth = np.abs(half[:, :2]) @ np.abs(step.way)
    return a["site_xpos"][ids, step.site, :2] + step.way * (INSERT_DEPTH - depth)[:, None]

  def _slide(self, step: Step) -> bool:
    return int(self.batch.model.jnt_type[step.joint]) == int(mujoco.mjtJoint.mjJNT_SLIDE)

  def _opening(self, step: Step, ids: np.ndarray) -> np.ndarray:
    """[n, 3] the world direction a slide's handle moves as its joint opens."""
    a, model = self.batch.data, self.batch.model
    axis = a["xaxis"][ids, step.joint]
    rule_sign = step.sign if step.atom.predicate == "open" else -step.sign
    return axis * rule_sign

  def _door_frame(self, step: Step, ids: np.ndarray, dq: np.ndarray | None = None):
    """(contact point [n, 3], radial [n, 3], closing direction [n, 3]) of a door's panel, the door
    turned by `dq` more than now: a point on the panel's face that the closing motion pushes
    into, PUSH_RADIUS of the way out from the hinge, PALM_CLEAR below the top."""
    a, model = self.batch.data, self.batch.model
    centre_b, half_b = _geom_box(model, step.part)
    mat = a["xmat"][ids, step.body].reshape(-1, 3, 3)
    anchor, axis = a["xanchor"][ids, step.joint], a["xaxis"][ids, step.joint]
    centre = a["xpos"][ids, step.body] + np.einsum("bij,j->bi", mat, centre_b)
    if dq is not None:
      rot = _rodrigues(axis, dq)
      centre = anchor + np.einsum("bij,bj->bi", rot, centre - anchor)
      mat = rot @ mat
    rel = centre - anchor
    radial = _unit(rel - (rel * axis).sum(-1, keepdims=True) * axis)
    closing = step.sign * np.cross(axis, radial)
    extent = lambda v: np.abs(np.einsum("bji,bj->bi", mat, v)) @ half_b  # the panel's half extent along v  # noqa: E731
    reach, depth = extent(radial), extent(closing)
    top = centre[:, 2] + extent(np.tile([0.0, 0.0, 1.0], (len(ids), 1)))
    r = np.linalg.norm(rel - (rel * axis).sum(-1, keepdims=True) * axis, axis=-1)
    point = centre + radial * (PUSH_RADIUS * (r + reach) - r)[:, None] - closing * depth[:, None]
    point[:, 2] = top + PALM_CLEAR - PALM_ABOVE
    return point, radial, closing

  def act(self, hand: np.ndarray, hand_mat: np.ndarray, target: np.ndarray, grip: np.ndarray) -> None:
    """Fill `target` [B, 3], `grip` [B] and the expert's goal orientation for the envs on one of
    our steps, and advance their phases; at a step's end hand the env to the plan's next step."""
    ex, a, model = self.expert, self.batch.data, self.batch.model
    for k, step in self.steps.items():
      ids = np.flatnonzero(ex.task == k)
      if not ids.size:
        continue
      new = self.entered[ids] != k
      if new.any():
        self._enter(k, step, ids[new], hand_mat[ids[new]])
      phase, count = self.phase[ids], self.count[ids] + 1
      tgt, g, ori = hand[ids].copy(), np.full(ids.size, -1.0), self.ori[ids].copy()
      away = self.away[ids]
      if step.kind == PULL:
        centre_b = _geom_box(model, step.part)[0]
        mat = a["xmat"][ids, step.body].reshape(-1, 3, 3)
        handle = a["xpos"][ids, step.body] + np.einsum("bij,j->bi", mat, centre_b)
        site = handle - away * PAD_IN
        q = a["qpos"][ids, model.jnt_qposadr[step.joint]]
        # the hand goes where the grasp puts it with the joint a lead further on (past the goal a little)
        q_cmd = q + np.clip(step.goal_q + step.sign * SLIDE_PAST - q, -SLIDE_LEAD, SLIDE_LEAD)
        axis = a["xaxis"][ids, step.joint]
        contact, pre = site, site + away * PRE_BACK
        drive = self.grip_pos[ids] + axis * (q_cmd - self.q0[ids])[:, None]
        g_drive = 1.0
        sel = phase <= IN  # the fingers half open: fully open they reach the drawers above and below
        g[sel] = self._preset(ids[sel], HANDLE_OPENING)
        sel = (phase == PRE) & (np.linalg.norm(pre[:, :2] - hand[ids, :2], axis=-1) > PRE_NEAR)
        if sel.any():  # over what stands on the way (not the drawer's own cabinet), then down; not up
          # (a climb first over the wine bottle by the reset pose changed LIBERO-Goal 3's way to its bowl)
          from envs.libero.expert import PALM_HALF_LENGTH
          top = ex._path_top(self.owner[k], ids[sel], hand[ids[sel], :2], pre[sel, :2])
          over = np.minimum(top + PALM_HALF_LENGTH + PRE_CLEARANCE, hand[ids[sel], 2])
          pre[sel, 2] = np.maximum(pre[sel, 2], over)
      elif step.kind == PUSH_JOINT and self._slide(step):  # the fingertips against the handle's front, pushing it in
        centre_b, half_b = _geom_box(model, step.part)
        mat = a["xmat"][ids, step.body].reshape(-1, 3, 3)
        handle = a["xpos"][ids, step.body] + np.einsum("bij,j->bi", mat, centre_b)
        depth = (np.abs(np.einsum("bji,bj->bi", mat, away)) @ half_b)[:, None]  # the handle's half depth
        face = handle + away * (depth + FINGER_HALF) - self.ori[ids][:, :, 2] * FINGERTIP  # the site, tips on the face
        contact = face + away * PUSH_BACK
        pre = contact + np.array([0.0, 0.0, SAFE_UP])
        q = a["qpos"][ids, model.jnt_qposadr[step.joint]]
        lead = np.clip(step.goal_q + step.sign * SLIDE_PAST - q, -SLIDE_LEAD, SLIDE_LEAD)
        drive = face + a["xaxis"][ids, step.joint] * lead[:, None]
        g_drive = 1.0
      elif step.kind == PUSH_JOINT:
        contact = self._door_frame(step, ids)[0] - self._door_frame(step, ids)[2] * (FINGER_HALF + PUSH_BACK)
        pre = contact + away * PRE_BACK
        pre[:, 2] = contact[:, 2] + SAFE_UP
        point, radial, closing = self._door_frame(step, ids, step.sign * np.full(ids.size, HINGE_LEAD))
        drive = point - closing * FINGER_HALF
        q = a["qpos"][ids, model.jnt_qposadr[step.joint]]
        sel = phase == DRIVE  # the hand turns with the door (its axis is vertical)
        ori[sel] = _yaw(q + step.sign * HINGE_LEAD - self.q0[ids])[sel] @ self.ori[ids[sel]]
        g_drive = 1.0
      elif step.kind == TWIST:
        mat = a["xmat"][ids, step.body].reshape(-1, 3, 3)
        contact = a["xpos"][ids, step.body] + np.einsum("bij,j->bi", mat, step.grip_local)
        pre = contact + np.array([0.0, 0.0, SAFE_UP])
        q = a["qpos"][ids, model.jnt_qposadr[step.joint]]
        dq = np.clip(step.goal_q + step.sign * TWIST_PAST - q, -TWIST_LEAD, TWIST_LEAD) + q - self.q0[ids]
        axis, anchor = a["xaxis"][ids, step.joint], a["xanchor"][ids, step.joint]
        rot = _rodrigues(axis, dq)
        drive = anchor + np.einsum("bij,bj->bi", rot, self.grip_pos[ids] - anchor)
        sel = phase == DRIVE
        ori[sel] = rot[sel] @ self.ori[ids[sel]]
        g_drive = 1.0
      elif step.kind == INSERT:  # the handle taken, lifted over the floor's edge, pushed in level
        from envs.libero.expert import _world_box
        mat = a["xmat"][ids, step.atom.body].reshape(-1, 3, 3)
        contact = a["xpos"][ids, step.atom.body] + np.einsum("bij,j->bi", mat, step.grip_local)
        way = np.c_[np.tile(step.way, (ids.size, 1)), np.zeros(ids.size)]
        pre = contact - way * INSERT_PRE
        lo, _ = _world_box(step.box, a["xpos"][ids, step.atom.body], mat)
        half = np.abs(a["site_xmat"][ids, step.site].reshape(-1, 3, 3) @ np.asarray(step.atom.size))
        need = a["site_xpos"][ids, step.site, 2] - half[:, 2] + INSERT_ABOVE - lo[:, 2]  # the rise still to go
        ahead = self._insert_goal(step, ids) - a["xpos"][ids, step.atom.body, :2]
        drive = hand[ids] + np.c_[np.where((need < INSERT_ABOVE / 2)[:, None], ahead, 0.0), need]
        g_drive = 1.0
      else:  # DRAG
        from envs.libero.expert import _world_box
        lo, hi = _world_box(step.box, a["xpos"][ids, step.atom.body], a["xmat"][ids, step.atom.body].reshape(-1, 3, 3))
        centre = (lo + hi) / 2
        goal = self._drag_goal(step, ids)
        u = _unit(goal - centre[:, :2])
        # the fingers pinch the dish's rim on its side toward the goal (one finger over the rim,
        # one outside it) and drag it there
        pinch = centre[:, :2] + u * PINCH_RADIUS
        z = lo[:, 2] + PINCH_HEIGHT
        contact, pre = np.c_[pinch, z], np.c_[pinch, hi[:, 2] + SAFE_UP]
        remaining = goal - centre[:, :2]
        # a little past the goal: the table's friction holds the plate back
        drive = np.c_[pinch + remaining + _unit(remaining) * DRAG_PAST, z]
        ori = self.ori[ids]
        g_drive = 1.0
      sel = phase == PRE
      tgt[sel] = pre[sel]
      sel = phase == IN
      tgt[sel] = contact[sel]
      sel = phase == GRIP
      tgt[sel], g[sel] = contact[sel], 1.0
      sel = phase == DRIVE
      tgt[sel], g[sel] = drive[sel], g_drive
      if step.kind == PUSH_JOINT:  # closed fingers push
        g[phase <= DRIVE] = 1.0
      sel = phase == RELEASE
      tgt[sel] = hand[ids[sel]]
      sel = phase == BACK
      tgt[sel] = self.back_from[ids[sel]]
      sel = (phase == RESTORE) | (phase == DONE)
      ori[sel] = self.down
      tgt[sel] = self.back_from[ids[sel]] + np.array([0.0, 0.0, SAFE_UP])
      # slow in the last approach and while driving: an overshoot knocks the handle's posts, a jerk slips the grasp
      slow = (phase == IN) | (phase == DRIVE)
      uncapped = tgt.copy()
      step_len = np.linalg.norm(tgt - hand[ids], axis=-1, keepdims=True)
      cap = np.where(phase == DRIVE, DRAG_STEP if step.kind == DRAG else DRIVE_STEP, SLOW_STEP)[:, None]
      capped = hand[ids] + (tgt - hand[ids]) * np.minimum(1.0, cap / np.maximum(step_len, 1e-9))
      tgt = np.where(slow[:, None], capped, tgt)
      # the controller has no integral term: a horizontal hand sags by up to a centimetre; near
      # its goal the hand's goal is moved by the error it keeps (integrated, bounded; not while a
      # drive's goal leads the hand on purpose)
      near = np.linalg.norm(tgt - hand[ids], axis=-1) < INTEGRAL_NEAR
      if step.joint >= 0:  # a drive integrates only while its joint is stuck (the arm short of force)
        stuck = np.abs(a["qvel"][ids, model.jnt_dofadr[step.joint]]) < DRIVE_STUCK
        near &= (phase != DRIVE) | stuck
      near &= step.kind == PULL
      self.integral[ids] = np.where(near[:, None], np.clip(self.integral[ids] + INTEGRAL_GAIN * (tgt - hand[ids]),
                                                           -INTEGRAL_MAX, INTEGRAL_MAX), self.integral[ids])
      tgt = tgt + self.integral[ids]
      target[ids], grip[ids], ex.goal_ori[ids] = tgt, g, ori

      err = np.linalg.norm(uncapped - hand[ids], axis=-1)
      rot_err = np.linalg.norm(_rotation_error(ori, hand_mat[ids]), axis=-1)
      done = np.zeros(ids.size, bool)
      done |= (phase == PRE) & (err < PRE_REACHED) & (rot_err < 0.1)  # a pre-pose: IN is the precise approach
      done |= (phase == IN) & (err < (IN_REACHED if step.kind == PULL else 0.006)) & (rot_err < 0.1)
      done |= (phase == GRIP) & ((count >= GRIP_STEPS) | (step.kind == PUSH_JOINT))  # nothing to grasp
      empty = np.abs(a["qpos"][ids][:, self._fingers]).sum(-1) < FINGERS_EMPTY  # closed on nothing: it slipped
      lost = (step.kind != PUSH_JOINT) & empty & (count > GRIP_STEPS)
      done |= (phase == DRIVE) & (self._reached(step, ids) | (count >= DRIVE_LIMIT) | lost)
      done |= (phase == RELEASE) & (count >= RELEASE_STEPS)
      done |= (phase == BACK) & (err < 0.015)
      # the hand turns back fully only for a next articulated step (its approach is planned from the
      # reset pose); a pick turns the hand while it moves above its object, and the plan's end needs no turn
      turn_back = k + 1 < len(ex.tasks) and (k + 1) in self.steps
      done |= (phase == RESTORE) & (err < 0.03) & ((rot_err < RESTORED) | (not turn_back))
      done |= (phase < DONE) & (phase != DRIVE) & (count >= PHASE_LIMIT)
      took = ids[done & (phase == GRIP)]  # the hold on the joint: where the twist or door turn starts from
      self.grip_pos[took] = hand[took]
      if step.joint >= 0:
        self.q0[took] = a["qpos"][took, model.jnt_qposadr[step.joint]]
      released = done & (phase == RELEASE)
      self.back_from[ids[released]] = hand[ids[released]] + away[released] * BACK_OFF
      backed = ids[done & (phase == BACK)]
      self.back_from[backed] = hand[backed]
      nxt = np.where(done, phase + 1, phase)
      # a step whose atom fails once the hand is back starts over (a slipped grasp, a stuck push),
      # in the step's own orientation: no turn back to the reset pose first
      again = (nxt == RESTORE) & (phase == BACK) & ~self._holds(step, ids) & (self.retries[ids] < RETRIES)
      self.retries[ids[again]] += 1
      nxt = np.where(again, PRE, nxt)
      self.phase[ids], self.count[ids] = nxt, np.where(done, 0, count)
      self.integral[ids[done]] = 0.0
      finished = ids[(nxt == DONE) & ((phase != DONE) | new)]  # (an atom that held on entry: at once)
      if not finished.size:
        continue
      if k + 1 < len(ex.tasks):  # the plan's next step, from its first phase
        ex.task[finished], ex.phase[finished], ex.count[finished], ex.fresh[finished] = k + 1, 0, 0, True
        ex.from_articulated[finished] = True
        self.retries[finished] = 0
      else:
        ex.phase[finished] = expert_done()


PUSH_RADIUS = 0.6  # where along a door (from the hinge to its far edge) it is pushed


def expert_done() -> int:
  from envs.libero.expert import DONE as done  # lazily: the expert imports this module
  return done


def _rotation_error(desired: np.ndarray, current: np.ndarray) -> np.ndarray:
  from envs.libero.expert import _rotation_error as error
  return error(desired, current)

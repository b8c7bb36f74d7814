"""A LIBERO task's success, its BDDL goal, evaluated on our state, batched over environments.

LIBERO's `_check_success` is the conjunction of the goal's atoms, each a predicate of
libero/libero/envs/predicates/base_predicates.py over the object states of
libero/libero/envs/object_states/base_object_states.py. We reimplement the ones the goals of
the five suites use, with LIBERO's thresholds and quirks, on arrays [B, ...] (numpy):
- On(a, b), b an object: b's body no higher than a's, their contact geoms touching, and their
  bodies within 3 cm in xy (`ObjectState.check_ontop`).
- On(a, r), r a region (a site): a's body in the slab from 5 mm below the top of r's box to 10 cm
  above it, inside its xy extent, and touching r's parent object if r has one
  (`SiteObject.under`; with LIBERO's own rotation of the offset, the site matrix applied as it
  is, not transposed).
- In(a, r), r a region: a's body strictly inside r's box grown by |R size| with 1 cm more below
  (`SiteObject.in_box`; LIBERO's contact test for a site is always true).
- Open / Close / TurnOn / TurnOff of an object or a region: its joints against the object's
  default ranges, by the comparison its class defines (articulated_objects.py); Open and TurnOn
  hold if any joint passes, Close and TurnOff if all do.
The goal itself is parsed by LIBERO's parser when the scene is built (`scene.describe`). Every
threshold sits in the compiled `Atom`, so a test can build a wrong predicate and see it caught.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import mujoco
import numpy as np

# LIBERO's thresholds (base_object_states.py, site_object.py), in metres.
ON_XY_RADIUS = 0.03  # ObjectState.check_ontop: bodies' xy distance below this
UNDER_BELOW = 0.005  # SiteObject.under: the object's offset along the site's z above size_z - this ...
UNDER_ABOVE = 0.10  # ... and below size_z + this (its `other_height`)
IN_BOX_BELOW = 0.01  # SiteObject.in_box: the box's lower bound lowered by this

# How LIBERO's articulated classes test their joints (articulated_objects.py): for each
# (predicate, class), the comparison and the end of the default range that is the threshold.
_OPENS_NEGATIVE = ("Microwave", "WoodenCabinet", "YellowCabinet", "WhiteCabinet")  # open: q below the open range's max
_OPENS_POSITIVE = ("ShortCabinet", "ShortFridge")  # open: q above the open range's min
_SWITCHES = ("FlatStove", "YellowStove")
_JOINT_RULES = {
  **{("open", c): ("<", "default_open_ranges", max) for c in _OPENS_NEGATIVE},
  **{("close", c): (">", "default_close_ranges", min) for c in _OPENS_NEGATIVE},
  **{("open", c): (">", "default_open_ranges", min) for c in _OPENS_POSITIVE},
  **{("close", c): ("<", "default_close_ranges", max) for c in _OPENS_POSITIVE},
  **{("turnon", c): (">=", "default_turnon_ranges", min) for c in _SWITCHES},
  **{("turnoff", c): ("<", "default_turnoff_ranges", max) for c in _SWITCHES}}
_QUANTIFIER = {"open": "any", "turnon": "any", "close": "all", "turnoff": "all"}
_COMPARE = {"<": np.less, ">": np.greater, ">=": np.greater_equal, "<=": np.less_equal}


@dataclasses.dataclass(frozen=True)
class Atom:
  """One atom of a goal, resolved to ids of the model and holding its thresholds."""
  predicate: str  # LIBERO's: on, in, open, close, turnon, turnoff
  args: tuple[str, ...]
  test: str  # ours: on_object, on_region, in_region, joints
  body: int = -1  # arg 1's root body (on, in)
  target_body: int = -1  # on_object: arg 2's root body
  site: int = -1  # on_region, in_region: the region's site
  size: tuple[float, ...] = ()  # the region's size, as LIBERO's SiteObject holds it
  touch: tuple[int, int] = (-1, -1)  # contact groups that must touch; -1: no contact test
  xy_radius: float = ON_XY_RADIUS
  under_below: float = UNDER_BELOW
  under_above: float = UNDER_ABOVE
  in_box_below: float = IN_BOX_BELOW
  qposadr: tuple[int, ...] = ()  # joints: the joints' qpos addresses
  compare: str = ""  # joints: q <compare> threshold
  threshold: float = 0.0
  quantifier: str = "any"  # joints: any or all of them


@dataclasses.dataclass(frozen=True, eq=False)
class Goal:
  """A task's goal compiled for one model: its atoms and the contact groups they read."""
  atoms: tuple[Atom, ...]
  groups: tuple[str, ...]  # objects whose contact geoms a test reads
  geom_group: np.ndarray  # [ngeom] int: a geom's index in `groups`, -1 if none
  # Where the model has our touch sensors (`touch_sensor_xml`): [S, 3] int rows of
  # (sensordata address, group, group), one per geom pair that can collide; else empty.
  touch_sensors: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3), np.int64))


class GoalInputs(NamedTuple):
  """What the goal reads of the state of B environments (MuJoCo's arrays, batched)."""
  xpos: np.ndarray  # [B, nbody, 3]
  xmat: np.ndarray  # [B, nbody, 9]
  site_xpos: np.ndarray  # [B, nsite, 3]
  site_xmat: np.ndarray  # [B, nsite, 9]
  qpos: np.ndarray  # [B, nq]
  touching: np.ndarray  # [B, G, G] bool: groups in contact (`touching`)


def _id(model: mujoco.MjModel, kind: mujoco.mjtObj, name: str) -> int:
  i = mujoco.mj_name2id(model, kind, name)
  if i < 0:
    raise ValueError(f"{kind.name[6:].lower()} {name!r} is not in the model: a model of another scene?")
  return i


def compile_goal(scene, model: mujoco.MjModel) -> Goal:
  """The goal of a scene (`scene.Scene`) resolved against its model (`scene.model`)."""
  meta = scene.meta
  objects, regions = meta["objects"], meta["regions"]
  groups: list[str] = []

  def group(name: str) -> int:
    if name not in groups:
      groups.append(name)
    return groups.index(name)

  def body(name: str) -> int:
    if name not in objects:
      raise ValueError(f"{meta['task']}: goal names {name!r}, which is no object of the scene")
    return _id(model, mujoco.mjtObj.mjOBJ_BODY, objects[name]["body"])

  def joint_atom(predicate: str, args: tuple, name: str) -> Atom:
    if name in regions:
      joints, owner = regions[name]["joints"], regions[name]["parent"]
    else:
      joints, owner = [j["name"] for j in objects[name]["joints"]], name
    cls = objects[owner]["class"]
    if (predicate, cls) not in _JOINT_RULES:
      raise NotImplementedError(f"{meta['task']}: LIBERO's {cls} has no {predicate} test we know "
                                f"(predicates._JOINT_RULES)")
    compare, ranges, end = _JOINT_RULES[predicate, cls]
    adr = []
    for j in joints:
      jid = _id(model, mujoco.mjtObj.mjOBJ_JOINT, j)
      if int(model.jnt_type[jid]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
        raise NotImplementedError(f"{meta['task']}: {predicate}({name}) reads joint {j}, which is not a hinge or slide")
      adr.append(int(model.jnt_qposadr[jid]))
    return Atom(predicate, args, "joints", qposadr=tuple(adr), compare=compare,
                threshold=float(end(objects[owner]["articulation"][ranges])), quantifier=_QUANTIFIER[predicate])

  atoms = []
  for atom in meta["goal"]:
    predicate, args = atom[0], tuple(atom[1:])
    if predicate in _QUANTIFIER:
      atoms.append(joint_atom(predicate, args, args[0]))
    elif predicate in ("on", "in") and args[1] in regions:
      region = regions[args[1]]
      site = _id(model, mujoco.mjtObj.mjOBJ_SITE, args[1])
      size = tuple(float(v) for v in region["size"])
      if predicate == "in":
        atoms.append(Atom(predicate, args, "in_region", body=body(args[0]), site=site, size=size))
      else:
        parent = region["parent"]
        touch = (group(parent), group(args[0])) if parent is not None else (-1, -1)
        atoms.append(Atom(predicate, args, "on_region", body=body(args[0]), site=site, size=size, touch=touch))
    elif predicate == "on":
      atoms.append(Atom(predicate, args, "on_object", body=body(args[0]), target_body=body(args[1]),
                        touch=(group(args[1]), group(args[0]))))
    else:
      raise NotImplementedError(f"{meta['task']}: goal atom {atom} is not one of the predicates reimplemented "
                                "here (on, in a region, open, close, turnon, turnoff)")
  geom_group = np.full(model.ngeom, -1, dtype=np.int32)
  for g, name in enumerate(groups):
    for geom in objects[name]["contact_geoms"]:
      gid = _id(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
      if geom_group[gid] >= 0:
        raise ValueError(f"geom {geom} belongs to both {groups[geom_group[gid]]} and {name}")
      geom_group[gid] = g
  sensors = []
  for i in range(model.nsensor):
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, i) or ""
    if name.startswith(TOUCH_SENSOR):
      a, b = int(model.sensor_objid[i]), int(model.sensor_refid[i])
      sensors.append((int(model.sensor_adr[i]), geom_group[a], geom_group[b]))
  return Goal(tuple(atoms), tuple(groups), geom_group, np.asarray(sensors, np.int64).reshape(-1, 3))


TOUCH_SENSOR = "skillplug_touch_"  # prefix of the contact sensors `touch_sensor_xml` adds


def _touch_pairs(meta: dict) -> list[tuple[str, str]]:
  """The (object, object) pairs whose contact a goal atom tests, as compile_goal pairs them."""
  objects, regions = meta["objects"], meta["regions"]
  pairs = []
  for atom in meta["goal"]:
    predicate, args = atom[0], tuple(atom[1:])
    if predicate == "on" and args[1] in regions and regions[args[1]]["parent"] is not None:
      pairs.append((regions[args[1]]["parent"], args[0]))
    elif predicate == "on" and args[1] in objects:
      pairs.append((args[1], args[0]))
  return pairs


def _can_collide(model: mujoco.MjModel, a: int, b: int) -> bool:
  """MuJoCo's contype/conaffinity filter (the only way LIBERO's scenes make contacts: no <pair>)."""
  return bool((model.geom_contype[a] & model.geom_conaffinity[b]) or (model.geom_contype[b] & model.geom_conaffinity[a]))


def touch_sensor_xml(scene, model: mujoco.MjModel) -> str:
  """A <sensor> section of MuJoCo contact sensors, one per pair of contact geoms of the goal's
  touching objects that can collide, each counting that pair's contacts (data="found"). The
  C batch does not list contacts; these read them inside the physics, as a position-stage
  sensor, and change nothing else of the model. A scene without contact tests gets none."""
  if model.npair or model.nexclude:
    raise NotImplementedError("the scene has explicit <pair> or <exclude> elements, which touch sensors "
                              "filtered by contype/conaffinity do not model")
  objects = scene.meta["objects"]
  lines, seen = [], set()
  for first, second in _touch_pairs(scene.meta):
    for ga in objects[first]["contact_geoms"]:
      for gb in objects[second]["contact_geoms"]:
        a, b = (_id(model, mujoco.mjtObj.mjOBJ_GEOM, g) for g in (ga, gb))
        if (ga, gb) in seen or not _can_collide(model, a, b):
          continue
        seen.add((ga, gb))
        lines.append(f'<contact name="{TOUCH_SENSOR}{len(lines)}" geom1="{ga}" geom2="{gb}" data="found" num="1"/>')
  return "<sensor>" + "".join(lines) + "</sensor>" if lines else ""


def touching_from_sensors(goal: Goal, sensordata: np.ndarray) -> np.ndarray:
  """[B, G, G] bool: which of the goal's contact groups touch, from our touch sensors' counts."""
  out = np.zeros((len(sensordata), len(goal.groups), len(goal.groups)), dtype=bool)
  if len(goal.touch_sensors):
    adr, a, b = goal.touch_sensors.T
    hit = np.asarray(sensordata)[:, adr] > 0  # [B, S]
    for ga, gb in set(zip(a.tolist(), b.tolist())):  # over the goal's touching pairs, a few
      any_hit = hit[:, (a == ga) & (b == gb)].any(axis=1)
      out[:, ga, gb] |= any_hit
      out[:, gb, ga] |= any_hit
  return out


def touching(goal: Goal, geom_pairs: np.ndarray, world: np.ndarray | None = None, batch: int = 1) -> np.ndarray:
  """[batch, G, G] bool: which of the goal's contact groups touch, from the contacts' geom pairs
  [K, 2] (MuJoCo's `contact.geom`, every contact the collision pass found, as robosuite's
  `check_contact` reads them) and, batched, each contact's environment `world` [K]."""
  pairs = np.asarray(geom_pairs, dtype=np.int64).reshape(-1, 2)
  world = np.zeros(len(pairs), np.int64) if world is None else np.asarray(world, np.int64)
  g = goal.geom_group[pairs] if len(pairs) else np.zeros((0, 2), np.int32)
  keep = (g[:, 0] >= 0) & (g[:, 1] >= 0)
  out = np.zeros((batch, len(goal.groups), len(goal.groups)), dtype=bool)
  out[world[keep], g[keep, 0], g[keep, 1]] = True
  out[world[keep], g[keep, 1], g[keep, 0]] = True
  return out


def state_of(goal: Goal, data: mujoco.MjData) -> GoalInputs:
  """The goal's inputs for one environment (B = 1) from an `MjData` after a forward pass."""
  return GoalInputs(data.xpos[None].copy(), data.xmat[None].copy(), data.site_xpos[None].copy(),
                    data.site_xmat[None].copy(), data.qpos[None].copy(), touching(goal, data.contact.geom))


def _touch(atom: Atom, s: GoalInputs) -> np.ndarray:
  a, b = atom.touch
  return s.touching[:, a, b] if a >= 0 else np.ones(len(s.qpos), dtype=bool)


def _on_object(atom: Atom, s: GoalInputs) -> np.ndarray:
  pa, pb = s.xpos[:, atom.body], s.xpos[:, atom.target_body]
  near = np.linalg.norm(pa[:, :2] - pb[:, :2], axis=-1) < atom.xy_radius
  return (pb[:, 2] <= pa[:, 2]) & _touch(atom, s) & near


def _site_frame(atom: Atom, s: GoalInputs) -> tuple[np.ndarray, np.ndarray]:
  return s.site_xpos[:, atom.site], s.site_xmat[:, atom.site].reshape(-1, 3, 3)


def _on_region(atom: Atom, s: GoalInputs) -> np.ndarray:
  origin, rot = _site_frame(atom, s)
  size = np.asarray(atom.size)
  d = np.einsum("bij,bj->bi", rot, s.xpos[:, atom.body] - origin)  # LIBERO: mat @ offset, as written
  slab = (size[2] - atom.under_below < d[:, 2]) & (d[:, 2] < size[2] + atom.under_above)
  return slab & np.all(np.abs(d[:, :2]) < size[:2], axis=-1) & _touch(atom, s)


def _in_region(atom: Atom, s: GoalInputs) -> np.ndarray:
  origin, rot = _site_frame(atom, s)
  half = np.abs(np.einsum("bij,j->bi", rot, np.asarray(atom.size)))
  lower, upper = origin - half, origin + half
  lower[:, 2] -= atom.in_box_below
  p = s.xpos[:, atom.body]
  return np.all(p > lower, axis=-1) & np.all(p < upper, axis=-1)


def _joints(atom: Atom, s: GoalInputs) -> np.ndarray:
  passed = _COMPARE[atom.compare](s.qpos[:, list(atom.qposadr)], atom.threshold)
  return passed.any(axis=-1) if atom.quantifier == "any" else passed.all(axis=-1)


_TESTS = {"on_object": _on_object, "on_region": _on_region, "in_region": _in_region, "joints": _joints}


def atom_values(goal: Goal, s: GoalInputs) -> np.ndarray:
  """[B, atoms] bool: each atom of the goal in each environment."""
  return np.stack([_TESTS[a.test](a, s) for a in goal.atoms], axis=-1)


def atom_name(atom: Atom) -> str:
  """An atom as the BDDL writes it: `In(akita_black_bowl_1, basket_1_contain_region)`."""
  names = {"turnon": "TurnOn", "turnoff": "TurnOff"}
  return f"{names.get(atom.predicate, atom.predicate.capitalize())}({', '.join(atom.args)})"


def satisfied(goal: Goal, s: GoalInputs) -> np.ndarray:
  """[B] bool: the goal holds (every atom), as LIBERO's `_check_success`."""
  return atom_values(goal, s).all(axis=-1)

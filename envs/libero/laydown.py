"""A tall object laid down on a tilted region (LIBERO-Goal 9: the wine bottle on the wine rack).

The rack's top is a board tilted about 31 degrees with a lip along its lower edge; a bottle stood
upright on it tips off once released. It is laid on its side instead, along the board's horizontal
edge, in the trough between the board and its lip, where it rests on both.

A bottle held at its neck from above ends up along the hand, which would then have to point
horizontally close to the robot's base, beyond the arm's reach (its elbow and wrist at their
limits). So it is grasped from the side at its neck, the hand level, pointing 45 degrees to the
right of the way from the robot's shoulder to the bottle (a reachable level pose, the hand above
the bowl beside the bottle and the rack's foot; pointing across that way, the hand of LIBERO-90 27
met the cabinet behind its bottle), the fingers closing horizontally, their width along the bottle.
Turning the hand a quarter turn about a horizontal axis then lays the bottle along the board's
edge, the hand pointing into the board (perpendicular to it), the fingers closing up and down the
slope. It is lowered along the board's normal to just above it, let go, and the hand backs off
along the normal. The bottle is 15 g: the pads' grip holds it in any orientation.

`LayDown` drives the envs whose current plan step is one of these (`applies` picks the atoms),
as `articulated.Articulated` drives its steps, and hands the env on at the end.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from envs.libero import predicates

LAY = "lay"
ABOVE, DOWN, IN, GRIP, LIFT, TURN, CARRY, LOWER, RELEASE, BACK, DONE = range(11)
PHASES = ("above", "down", "in", "grip", "lift", "turn", "carry", "lower", "release", "back", "done")
TILT_MIN = np.radians(20)  # rad: a region's board tilted more than this from level ...
TALL = 2.0  # ... and an object this many times taller than wide: laid down, not stood up
BOARD_NEAR = 0.01  # m: the board is the parent's largest colliding geom this close to the region's site
GRIP_BELOW_TOP = 0.033  # m below the object's top the fingers close across it (the bottle's neck: the
#                         hand clear of the bowl beside it and the rack's foot)
GRASP_TURN = -np.pi / 4  # rad: the level hand points this far (about the vertical) off the way from the shoulder
PRE_BACK = 0.12  # m the hand waits back from the grasp along its pointing direction ...
PRE_UP = 0.12  # ... and this far above it, while it turns level
LIFT_UP = 0.2  # m the object is lifted before the hand turns (its bottom swings up to the hand's height)
UP_SLOPE = 0.03  # m: the bottom is put this far up the board's slope from the region's site (then slides to the lip)
DROP = 0.012  # m over the board the object's side is let go (the fingertips clear the lip)
ALONG_BACK = 0.03  # m: the bottom is this far from the region's site along the board's edge (the
#                    object's middle near the region's middle, clear of the rack's post)
PLACE_ABOVE = 0.08  # m along the board's normal the hand comes in from
SLOW_STEP = 0.015  # m: the most the hand's goal leads it by on the way in and down
BACK_OFF = 0.10  # m along the normal after letting go
CLOSE_STEPS, RELEASE_STEPS = 12, 10
REACHED, TURNED = 0.006, 0.05  # m, rad
CARRIED = 0.015  # m
PHASE_LIMIT = 80  # control steps before a phase gives up waiting


@dataclasses.dataclass(frozen=True)
class Step:
  """One lay-down atom resolved to ids: the object, its box and radius, the region's board."""
  kind: str
  atom: predicates.Atom
  box: np.ndarray  # [2, 3] the object's collision box in its body frame
  radius: float  # m: the object's largest horizontal half extent (its side's height when laid down)
  board_body: int
  board_centre: np.ndarray  # the board geom's centre in its body's frame ...
  board_rot: np.ndarray  # ... its axes
  board_half: np.ndarray  # ... and half sizes
  normal_axis: int  # which of the board's axes is its thin one


def _board(model: mujoco.MjModel, scene, atom: predicates.Atom):
  """(body, centre, rot, half, thin axis) of the board the region's site sits on, or None."""
  from envs.libero import articulated
  parent = scene.meta["regions"][atom.args[1]]["parent"]
  if parent is None:
    return None
  body = model.body(scene.meta["objects"][parent]["body"]).id
  d = mujoco.MjData(model)
  mujoco.mj_forward(model, d)
  site = d.site_xpos[atom.site]
  best = None
  for g in range(model.ngeom):
    b = int(model.geom_bodyid[g])
    if b != body or not (model.geom_contype[g] or model.geom_conaffinity[g]) or model.geom_type[g] != mujoco.mjtGeom.mjGEOM_BOX:
      continue
    local = d.geom_xmat[g].reshape(3, 3).T @ (site - d.geom_xpos[g])
    gap = np.linalg.norm(np.maximum(np.abs(local) - model.geom_size[g], 0.0))
    area = np.prod(np.sort(model.geom_size[g])[1:])
    if gap < BOARD_NEAR and (best is None or area > best[0]):
      best = (area, g)
  if best is None:
    return None
  g = best[1]
  rot = np.zeros(9)
  mujoco.mju_quat2Mat(rot, model.geom_quat[g])
  centre, _ = articulated._geom_box(model, g)
  return body, centre, rot.reshape(3, 3), model.geom_size[g].copy(), int(np.argmin(model.geom_size[g]))


def applies(model: mujoco.MjModel, scene, atom: predicates.Atom) -> bool:
  """On(region) of a tall object onto a region whose board is tilted: laid down."""
  if atom.test != "on_region":
    return False
  from envs.libero.expert import _box
  box = _box(model, atom.body)
  extent = box[1] - box[0]
  if extent[2] < TALL * extent[:2].max():
    return False
  board = _board(model, scene, atom)
  if board is None:
    return False
  body, _, rot, _, thin = board
  d = mujoco.MjData(model)
  mujoco.mj_forward(model, d)
  normal = d.xmat[body].reshape(3, 3) @ rot[:, thin]
  return bool(np.arccos(min(abs(normal[2]), 1.0)) > TILT_MIN)


def make_step(batch, atom: predicates.Atom) -> Step:
  from envs.libero.expert import _box
  model = batch.model
  body, centre, rot, half, thin = _board(model, batch.scene, atom)
  box = _box(model, atom.body)
  return Step(LAY, atom, box, float(np.abs(box[:, :2]).max()), body, centre, rot, half, thin)


def _unit(v: np.ndarray) -> np.ndarray:
  return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


class LayDown:
  """The lay-down steps of an `expert.Expert`'s plan, for the envs whose current step is one."""

  def __init__(self, expert, steps: dict[int, Step]):
    self.expert, self.batch, self.steps = expert, expert.batch, steps
    n = self.batch.num_envs
    self.entered = np.full(n, -1)  # the plan step each env's state below belongs to
    self.phase = np.zeros(n, np.int64)
    self.count = np.zeros(n, np.int64)
    self.grasp_ori = np.zeros((n, 3, 3))  # the flat side grasp
    self.place_ori = np.zeros((n, 3, 3))  # pointing into the board
    self.held = np.zeros((n, 3))  # the object's bottom in the hand's frame, once lifted
    self.carry_z = np.zeros(n)
    self.back_from = np.zeros((n, 3))
    self._shoulder = int(self.batch.model.jnt_bodyid[self.batch.model.joint(
        self.batch.scene.meta["robot"]["arm_joints"][0]["name"]).id])

  def _frame(self, step: Step, ids: np.ndarray):
    """(normal, up-slope, along [n, 3] unit vectors; top-surface centre [n, 3]) of the board."""
    a = self.batch.data
    mat = a["xmat"][ids, step.board_body].reshape(-1, 3, 3)
    axes = np.einsum("bij,jk->bik", mat, step.board_rot)  # columns: the board's axes in the world
    normal = axes[:, :, step.normal_axis]
    normal = normal * np.sign(normal[:, 2:3])
    up = _unit(np.array([0.0, 0.0, 1.0]) - normal * normal[:, 2:3])
    along = np.cross(normal, up)
    centre = a["xpos"][ids, step.board_body] + np.einsum("bij,j->bi", mat, step.board_centre)
    top = centre + normal * step.board_half[step.normal_axis]
    return normal, up, along, top

  def _enter(self, k: int, step: Step, ids: np.ndarray) -> None:
    """Plan both orientations: the grasp's (the hand level, pointing GRASP_TURN off the way from the
    robot's shoulder to the object, the fingers' width vertical: along the object), and the
    place's (the hand pointing into the board, the object along the board's edge, the fingers up
    and down the slope), of its two the one the lesser turn from the grasp's."""
    from envs.libero.articulated import _rodrigues
    a = self.batch.data
    normal, _, along, _ = self._frame(step, ids)
    pos = a["xpos"][ids, step.atom.body]
    out = _unit((pos - a["xpos"][ids, self._shoulder]) * [1.0, 1.0, 0.0])
    p = np.einsum("bij,bj->bi", _rodrigues(np.tile([0.0, 0.0, 1.0], (len(ids), 1)), np.full(len(ids), GRASP_TURN)), out)
    y = np.tile([0.0, 0.0, -1.0], (len(ids), 1))  # the site's y down: the reachable roll of a level hand
    grasp = np.stack([np.cross(y, p), y, p], -1)
    best = None
    for sign in (1.0, -1.0):
      y2, z2 = sign * along, -normal
      place = np.stack([np.cross(y2, z2), y2, z2], -1)
      angle = np.arccos(np.clip((np.trace(place @ np.swapaxes(grasp, 1, 2), axis1=1, axis2=2) - 1) / 2, -1, 1))
      if best is None:
        best = [place, angle]
      else:
        pick = angle < best[1]
        best = [np.where(pick[:, None, None], place, best[0]), np.minimum(angle, best[1])]
    self.place_ori[ids], self.grasp_ori[ids] = best[0], grasp
    self.entered[ids], self.phase[ids], self.count[ids] = k, ABOVE, 0

  def _place(self, step: Step, ids: np.ndarray) -> np.ndarray:
    """[n, 3] where the object's bottom goes: on the board's top, UP_SLOPE above the region's site
    (it slides down to the lip), its side DROP over the board."""
    a = self.batch.data
    normal, up, _, top = self._frame(step, ids)
    site = a["site_xpos"][ids, step.atom.site]
    axis = -self.place_ori[ids][:, :, 1]  # the object's axis, bottom to top (the site's y points to its bottom)
    on = site - normal * ((site - top) * normal).sum(-1, keepdims=True)  # the site dropped onto the board
    return on + up * UP_SLOPE + normal * (step.radius + DROP) - axis * ALONG_BACK

  def act(self, hand: np.ndarray, hand_mat: np.ndarray, target: np.ndarray, grip: np.ndarray) -> None:
    ex, a = self.expert, self.batch.data
    from envs.libero.expert import _rotation_error, DONE as EXPERT_DONE
    for k, step in self.steps.items():
      ids = np.flatnonzero(ex.task == k)
      if not ids.size:
        continue
      new = self.entered[ids] != k
      if new.any():
        self._enter(k, step, ids[new])
      phase, count = self.phase[ids], self.count[ids] + 1
      body = step.atom.body
      mat = a["xmat"][ids, body].reshape(-1, 3, 3)
      bottom = a["xpos"][ids, body]
      grasp = bottom + mat[:, :, 2] * (step.box[1, 2] - GRIP_BELOW_TOP)
      g_ori = self.grasp_ori[ids]
      point = g_ori[:, :, 2]
      pre = grasp - point * PRE_BACK
      tgt, g, ori = hand[ids].copy(), np.full(ids.size, -1.0), g_ori.copy()
      sel = phase == ABOVE
      tgt[sel] = pre[sel] + [0.0, 0.0, PRE_UP]
      sel = phase == DOWN
      tgt[sel] = pre[sel]
      sel = phase == IN
      tgt[sel] = grasp[sel]
      sel = phase == GRIP
      tgt[sel], g[sel] = grasp[sel], 1.0
      normal = self._frame(step, ids)[0]
      place = self._place(step, ids)
      sel = phase == LIFT
      tgt[sel] = np.c_[hand[ids[sel], :2], self.carry_z[ids[sel]]]
      g[sel] = 1.0
      sel = phase >= TURN
      ori[sel] = self.place_ori[ids[sel]]
      hand_at = place - np.einsum("bij,bj->bi", self.place_ori[ids], self.held[ids])  # the hand with the bottom at `place`
      sel = phase == TURN
      tgt[sel], g[sel] = np.c_[hand[ids[sel], :2], self.carry_z[ids[sel]]], 1.0
      sel = phase == CARRY
      tgt[sel], g[sel] = hand_at[sel] + normal[sel] * PLACE_ABOVE, 1.0
      sel = phase == LOWER
      tgt[sel], g[sel] = hand_at[sel], 1.0
      sel = phase == RELEASE
      tgt[sel] = hand[ids[sel]]
      sel = (phase == BACK) | (phase == DONE)
      tgt[sel] = self.back_from[ids[sel]]
      uncapped = tgt.copy()
      slow = (phase == IN) | (phase == LOWER) | (phase == DOWN)
      step_len = np.linalg.norm(tgt - hand[ids], axis=-1, keepdims=True)
      capped = hand[ids] + (tgt - hand[ids]) * np.minimum(1.0, SLOW_STEP / np.maximum(step_len, 1e-9))
      tgt = np.where(slow[:, None], capped, tgt)
      target[ids], grip[ids], ex.goal_ori[ids] = tgt, g, ori

      err = np.linalg.norm(uncapped - hand[ids], axis=-1)
      rot = np.linalg.norm(_rotation_error(ori, hand_mat[ids]), axis=-1)
      done = np.zeros(ids.size, bool)
      done |= (phase == ABOVE) & (err < 0.02) & (rot < TURNED)
      done |= (phase == DOWN) & (err < 0.01)
      done |= (phase == IN) & (err < REACHED)
      done |= (phase == GRIP) & (count >= CLOSE_STEPS)
      done |= (phase == LIFT) & (err < 0.02)
      done |= (phase == TURN) & (rot < TURNED)
      done |= (phase == CARRY) & (err < CARRIED) & (rot < TURNED)
      done |= (phase == LOWER) & (err < REACHED)
      done |= (phase == RELEASE) & (count >= RELEASE_STEPS)
      done |= (phase == BACK) & (err < 0.02)
      done |= (phase < DONE) & (count >= PHASE_LIMIT) & (phase != GRIP) & (phase != RELEASE)
      gripped = ids[done & (phase == GRIP)]
      self.carry_z[gripped] = hand[gripped, 2] + LIFT_UP
      lifted = ids[done & (phase == LIFT)]
      self.held[lifted] = np.einsum("bji,bj->bi", hand_mat[lifted], a["xpos"][lifted, body] - hand[lifted])
      released = ids[done & (phase == RELEASE)]
      self.back_from[released] = hand[released] + normal[done & (phase == RELEASE)] * BACK_OFF
      nxt = np.where(done, phase + 1, phase)
      self.phase[ids], self.count[ids] = nxt, np.where(done, 0, count)
      finished = ids[(nxt == DONE) & (phase != DONE)]
      if not finished.size:
        continue
      if k + 1 < len(ex.tasks):
        ex.task[finished], ex.phase[finished], ex.count[finished], ex.fresh[finished] = k + 1, 0, 0, True
        ex.from_articulated[finished] = True
      else:
        ex.phase[finished] = EXPERT_DONE

"""LIBERO in our engine, stage 1 (envs/libero, docs/libero.md), judged by LIBERO's own environment:
the suites as LIBERO lists them; our MjData at a benchmark init state where the reference env puts
every body; our goal predicate against the reference `_check_success` on the init states, on
states where the goal holds (objects placed on or in their targets, joints set) and on states a
hair either side of each threshold, so that a predicate with a threshold off is caught.

A reference env takes 7-12 s to build: one per task, module-scoped. The default run checks one
task per suite (their goals use every test: on an object, on a region with and without a parent,
in a region, a switch); the rest of the four suites are marked `sweep` (`make test-libero`).
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from envs.libero import installed, predicates, scene, suites

ROOT = Path(__file__).resolve().parents[1]
FOUR = ("libero_spatial", "libero_object", "libero_goal", "libero_10")
# One task per suite, together covering every test of predicates.py (and a fixture to place).
DEFAULT = (("libero_spatial", 4), ("libero_object", 0), ("libero_goal", 5), ("libero_10", 2))
SLOW = tuple((s, i) for s in FOUR for i in range(10) if (s, i) not in DEFAULT)
POSITION_TOL = 1e-6  # m
EPS = 1e-4  # how far either side of a threshold the boundary states sit (m or rad)
RANGE_OF = {"open": "default_open_ranges", "close": "default_close_ranges",
            "turnon": "default_turnon_ranges", "turnoff": "default_turnoff_ranges"}


# ---------------------------------------------------------------- the suites

def test_suites_list_their_tasks_instructions_files_and_init_states():
  for suite in suites.SUITES:
    tasks = suites.tasks(suite)
    assert len(tasks) == (90 if suite == "libero_90" else 10), suite
    assert len({t.name for t in tasks}) == len(tasks)
    for t in tasks:
      assert t.language.strip() and Path(t.bddl_file).is_file(), t
      assert t.time_limit == suites.TIME_LIMITS[suite]
  assert [suites.TIME_LIMITS[s] for s in FOUR] == [220, 280, 300, 520]
  for suite in FOUR:
    for t in suites.tasks(suite):
      states = suites.init_states(suite, t.index)
      assert states.shape[0] == suites.INIT_STATES_PER_TASK and states.ndim == 2 and np.isfinite(states).all()
  assert suites.task("libero_object", "pick_up_the_ketchup_and_place_it_in_the_basket").index == 4


def test_unknown_suite_task_and_missing_libero_say_what_is_wrong():
  with pytest.raises(ValueError, match="unknown LIBERO suite 'libero_100'.*libero_spatial"):
    suites.tasks("libero_100")
  with pytest.raises(ValueError, match="unknown task 10 of LIBERO suite 'libero_goal'"):
    suites.task("libero_goal", 10)
  with pytest.raises(installed.LiberoMissing, match="make install"):
    installed.libero_module("libero.libero.no_such_module")


def test_importing_envs_and_envs_libero_loads_neither_libero_nor_robosuite():
  code = ("import sys, envs, envs.libero, envs.libero.suites, envs.libero.scene, envs.libero.predicates; "
          "print(sorted(m for m in ('libero', 'robosuite', 'bddl') if m in sys.modules))")
  out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
  assert out.stdout.strip() == "[]", out.stdout + out.stderr


# ---------------------------------------------------------------- a task against its reference env

@dataclasses.dataclass
class Case:
  suite: str
  index: int
  env: object  # the reference OffScreenRenderEnv
  scene: scene.Scene
  model: mujoco.MjModel
  data: mujoco.MjData
  goal: predicates.Goal
  states: np.ndarray  # the benchmark's init states


def make_case(suite: str, index: int) -> Case:
  env = scene.reference_env(suite, index)
  s = scene.cached(suite, index) or scene.build_scene(suite, index, env=env)
  m = scene.model(s)
  return Case(suite, index, env, s, m, mujoco.MjData(m), predicates.compile_goal(s, m),
              suites.init_states(suite, index))


def reference_success(case: Case, qpos: np.ndarray) -> bool:
  """The reference env's `_check_success` with `qpos` written into its sim (qvel 0)."""
  case.env.sim.data.qpos[:] = qpos
  case.env.sim.data.qvel[:] = 0.0
  case.env.sim.forward()
  return bool(case.env.check_success())


def our_inputs(case: Case, qpos: np.ndarray) -> predicates.GoalInputs:
  case.data.qpos[:] = qpos
  case.data.qvel[:] = 0.0
  mujoco.mj_forward(case.model, case.data)
  return predicates.state_of(case.goal, case.data)


def free_qposadr(case: Case, obj: str) -> int:
  free = [j for j in case.scene.meta["objects"][obj]["joints"] if j["type"] == "free"]
  assert len(free) == 1, (obj, case.scene.meta["objects"][obj]["joints"])
  return free[0]["qposadr"]


def with_position(case: Case, qpos: np.ndarray, obj: str, pos) -> np.ndarray:
  out = qpos.copy()
  adr = free_qposadr(case, obj)
  out[adr:adr + 3] = pos
  return out


def touches(case: Case, qpos: np.ndarray, a: int, b: int) -> bool:
  return bool(our_inputs(case, qpos).touching[0, a, b])


def dropped(case: Case, qpos: np.ndarray, obj: str, xy, group: int, support: int, z_from: float) -> np.ndarray | None:
  """qpos with `obj` at `xy`, lowered from `z_from` until it first touches `support` (5 mm steps,
  then bisection to 0.1 mm), then 1 mm lower; None where it touches nothing within 40 cm."""
  at = lambda z: with_position(case, qpos, obj, (*xy, z))  # noqa: E731
  if touches(case, at(z_from), group, support):
    return None
  hi = z_from
  for lo in z_from - 0.005 * np.arange(1, 81):
    if touches(case, at(lo), group, support):
      break
    hi = lo
  else:
    return None
  while hi - lo > 1e-4:
    mid = (hi + lo) / 2
    if touches(case, at(mid), group, support):
      lo = mid
    else:
      hi = mid
  return at(lo - 1e-3)


def site_frame(case: Case, qpos: np.ndarray, site: int) -> tuple[np.ndarray, np.ndarray]:
  our_inputs(case, qpos)
  return case.data.site_xpos[site].copy(), case.data.site_xmat[site].reshape(3, 3).copy()


def body_position(case: Case, qpos: np.ndarray, body: int) -> np.ndarray:
  our_inputs(case, qpos)
  return case.data.xpos[body].copy()


def set_joints(atom: predicates.Atom, qpos: np.ndarray, value: float) -> np.ndarray:
  out = qpos.copy()
  out[list(atom.qposadr)] = value
  return out


def goal_states(case: Case) -> list[tuple[str, np.ndarray]]:
  """(label, qpos): first a state where every atom of the goal holds, built from init state 0
  (joints set inside LIBERO's default range for the predicate, then each object placed: into
  its region's centre, or lowered onto its target until it touches), then for each atom states
  a hair either side of its thresholds, the rest of the goal left holding."""
  meta = case.scene.meta
  qpos = case.states[0][1:1 + case.model.nq].copy()
  joints = [a for a in case.goal.atoms if a.test == "joints"]
  for atom in joints:
    owner = meta["regions"][atom.args[0]]["parent"] if atom.args[0] in meta["regions"] else atom.args[0]
    qpos = set_joints(atom, qpos, float(np.mean(meta["objects"][owner]["articulation"][RANGE_OF[atom.predicate]])))
  placed = {}  # atom index -> how it was placed, for the boundary states
  for k, atom in enumerate(case.goal.atoms):
    obj = atom.args[0] if atom.test != "joints" else None
    if atom.test == "in_region":
      origin, rot = site_frame(case, qpos, atom.site)
      qpos = with_position(case, qpos, obj, origin)
      placed[k] = (origin, rot)
    elif atom.test == "on_region":
      origin, rot = site_frame(case, qpos, atom.site)
      # LIBERO offsets by rot @ (p - origin): p = origin + rot.T @ d puts the offset at d.
      centre = origin + rot.T @ np.array([0.0, 0.0, atom.size[2] + 0.03])
      if atom.touch[0] >= 0:
        new = dropped(case, qpos, obj, centre[:2], atom.touch[1], atom.touch[0], centre[2] + 0.1)
        assert new is not None, f"{case.suite} {case.index}: {obj} touches no {atom.args[1]} parent"
        qpos = new
      else:
        qpos = with_position(case, qpos, obj, centre)
      placed[k] = (origin, rot)
    elif atom.test == "on_object":
      target = body_position(case, qpos, atom.target_body)
      new = dropped(case, qpos, obj, target[:2], atom.touch[1], atom.touch[0], target[2] + 0.25)
      assert new is not None, f"{case.suite} {case.index}: {obj} touches no {atom.args[1]}"
      qpos = new
      placed[k] = target
  states = [("goal", qpos)]
  for k, atom in enumerate(case.goal.atoms):
    obj = atom.args[0] if atom.test != "joints" else None
    tag = f"{atom.predicate}{atom.args}"
    if atom.test == "joints":
      for delta in (-EPS, 0.0, EPS):
        states.append((f"{tag} q=threshold{delta:+g}", set_joints(atom, qpos, atom.threshold + delta)))
    elif atom.test == "in_region":
      origin, rot = placed[k]
      half = np.abs(rot @ np.asarray(atom.size))
      for axis in range(3):
        for side in (-1, 1):
          bound = half[axis] + (atom.in_box_below if axis == 2 and side < 0 else 0.0)
          for delta in (-EPS, EPS):
            p = origin.copy()
            p[axis] += side * (bound + delta)
            states.append((f"{tag} axis {axis} side {side:+d} {delta:+g}", with_position(case, qpos, obj, p)))
    elif atom.test == "on_region":
      origin, rot = placed[k]
      p0 = body_position(case, qpos, atom.body)
      d0 = rot @ (p0 - origin)
      offsets = [(axis, side * (atom.size[axis] + delta))
                 for axis in (0, 1) for side in (-1, 1) for delta in (-EPS, EPS)]
      if atom.touch[0] < 0:  # no contact test: the slab's two faces too
        offsets += [(2, atom.size[2] - atom.under_below + delta) for delta in (-EPS, EPS)]
        offsets += [(2, atom.size[2] + atom.under_above + delta) for delta in (-EPS, EPS)]
      for axis, value in offsets:
        d = d0.copy()
        d[axis] = value
        p = origin + rot.T @ d
        new = with_position(case, qpos, obj, p)
        if atom.touch[0] >= 0 and axis < 2:  # keep it resting on the parent
          new = dropped(case, qpos, obj, p[:2], atom.touch[1], atom.touch[0], p[2] + 0.1)
          if new is None:
            continue
        states.append((f"{tag} d[{axis}]={value:+.4f}", new))
    elif atom.test == "on_object":
      target = placed[k]
      for delta in (-EPS, EPS):
        xy = target[:2] + np.array([atom.xy_radius + delta, 0.0])
        new = dropped(case, qpos, obj, xy, atom.touch[1], atom.touch[0], target[2] + 0.25)
        if new is not None:
          states.append((f"{tag} xy={atom.xy_radius + delta:.4f}", new))
      lifted = qpos.copy()
      adr = free_qposadr(case, obj)
      lifted[adr + 2] += 0.005  # above its target, not touching it
      states.append((f"{tag} lifted 5 mm", lifted))
  return states


@dataclasses.dataclass
class Judged:
  case: Case
  labels: list[str]
  qpos: np.ndarray  # [N, nq]
  reference: np.ndarray  # [N] bool: the reference's _check_success
  init_reference: np.ndarray  # [50] bool


def judge(case: Case) -> Judged:
  labelled = goal_states(case)
  ref = np.array([reference_success(case, q) for _, q in labelled])
  init_ref = np.array([reference_success(case, st[1:1 + case.model.nq]) for st in case.states])
  return Judged(case, [l for l, _ in labelled], np.stack([q for _, q in labelled]), ref, init_ref)


def ours(j: Judged, goal: predicates.Goal | None = None) -> np.ndarray:
  goal = goal or j.case.goal
  return np.array([predicates.satisfied(goal, our_inputs(j.case, q))[0] for q in j.qpos])


def check_init_state_parity(case: Case) -> None:
  """Our MjData at init state i against the reference after its own `set_init_state(i)`."""
  eef = mujoco.mj_name2id(case.model, mujoco.mjtObj.mjOBJ_SITE, case.scene.meta["robot"]["eef_site"])
  assert case.states.shape == (suites.INIT_STATES_PER_TASK, case.scene.meta["state_width"])
  for i in (0, 1, 25, 49):
    case.env.set_init_state(case.states[i])
    scene.set_init_state(case.model, case.data, case.states[i])
    ref = case.env.sim.data
    assert np.abs(case.data.xpos - ref.body_xpos).max() <= POSITION_TOL, (case.suite, case.index, i)
    assert np.abs(case.data.site_xpos[eef] - ref.site_xpos[eef]).max() <= POSITION_TOL
    assert np.abs(case.data.xquat - ref.body_xquat).max() <= 1e-6
  # The comparison can fail: the objects of another init state sit elsewhere.
  scene.set_init_state(case.model, case.data, case.states[1])
  case.env.set_init_state(case.states[0])
  assert np.abs(case.data.xpos - case.env.sim.data.body_xpos).max() > 100 * POSITION_TOL
  with pytest.raises(ValueError, match="1 \\+ nq \\+ nv"):
    scene.set_init_state(case.model, case.data, case.states[0][:-1])


def check_goal_agreement(j: Judged) -> dict:
  c = j.case
  assert not j.init_reference.any(), "a benchmark init state already satisfies the goal"
  init_ours = np.array([predicates.satisfied(c.goal, our_inputs(c, st[1:1 + c.model.nq]))[0] for st in c.states])
  assert (init_ours == j.init_reference).all()
  mine = ours(j)
  wrong = [l for l, a, b in zip(j.labels, mine, j.reference) if a != b]
  assert not wrong, f"{c.suite} {c.index}: ours and the reference disagree on {wrong}"
  assert j.reference[0], f"{c.suite} {c.index}: the built goal state does not satisfy the reference"
  assert not j.reference.all(), "no boundary state falls outside the goal"
  return {"init": len(c.states), "built": len(mine), "goal_true": int(mine.sum())}


def mutations(atom: predicates.Atom) -> list[tuple[str, predicates.Atom]]:
  """Wrong versions of an atom: each threshold off, each comparison loosened or tightened."""
  r = dataclasses.replace
  if atom.test == "joints":
    flip = {"<": "<=", ">": ">=", ">=": ">", "<=": "<"}[atom.compare]
    return [("threshold +1 mm", r(atom, threshold=atom.threshold + 1e-3)),
            ("threshold -1 mm", r(atom, threshold=atom.threshold - 1e-3)),
            (f"{atom.compare} as {flip}", r(atom, compare=flip))]
  if atom.test == "in_region":
    return [("no 1 cm below", r(atom, in_box_below=0.0)),
            ("box 1 mm larger", r(atom, size=tuple(v + 1e-3 for v in atom.size)))]
  if atom.test == "on_region":
    out = [("region 1 mm larger in xy", r(atom, size=(atom.size[0] + 1e-3, atom.size[1] + 1e-3, atom.size[2])))]
    if atom.touch[0] < 0:
      out += [("slab 1 mm lower", r(atom, under_below=atom.under_below + 1e-3)),
              ("slab 1 mm shorter", r(atom, under_above=atom.under_above - 1e-3))]
    return out
  return [("xy radius +1 mm", r(atom, xy_radius=atom.xy_radius + 1e-3)),
          ("xy radius -1 mm", r(atom, xy_radius=atom.xy_radius - 1e-3)),
          ("no contact test", r(atom, touch=(-1, -1)))]


def check_wrong_predicates_are_caught(j: Judged) -> None:
  goal = j.case.goal
  for k, atom in enumerate(goal.atoms):
    for what, wrong in mutations(atom):
      mutated = dataclasses.replace(goal, atoms=goal.atoms[:k] + (wrong,) + goal.atoms[k + 1:])
      assert (ours(j, mutated) != j.reference).any(), (
        f"{j.case.suite} {j.case.index}: {atom.predicate}{atom.args} with {what} agrees with the reference everywhere")


@pytest.fixture(scope="module", params=DEFAULT, ids=[f"{s}-{i}" for s, i in DEFAULT])
def judged(request):
  case = make_case(*request.param)
  yield judge(case)
  case.env.close()


def test_scene_is_the_reference_model_and_round_trips_its_cache(judged, tmp_path):
  c = judged.case
  fresh = scene.build_scene(c.suite, c.index, cache=tmp_path, env=c.env)
  assert scene.cached(c.suite, c.index, cache=tmp_path).meta == fresh.meta
  # The cached scene (maybe from an earlier run) places the fixtures where this reset did.
  assert c.scene.meta["body_overrides"] == fresh.meta["body_overrides"]
  ref = c.env.sim.model._model
  for name in ("body_pos", "body_quat", "geom_size", "geom_pos", "mesh_vert", "jnt_range", "site_rgba"):
    assert np.array_equal(getattr(c.model, name), getattr(ref, name)), name
  parse = installed.libero_module("libero.libero.envs.bddl_utils").robosuite_parse_problem
  assert c.scene.goal == [list(a) for a in parse(c.scene.task.bddl_file)["goal_state"]]
  fresh.xml_path.write_text(fresh.xml_path.read_text() + " ")
  assert scene.cached(c.suite, c.index, cache=tmp_path) is None  # a changed MJCF is not used


def test_init_states_put_every_body_where_the_reference_does(judged):
  check_init_state_parity(judged.case)


def test_goal_agrees_with_the_reference_on_init_goal_and_boundary_states(judged):
  counts = check_goal_agreement(judged)
  print(judged.case.suite, judged.case.index, counts)


def test_a_predicate_with_a_wrong_threshold_is_caught(judged):
  check_wrong_predicates_are_caught(judged)


def test_batched_goal_matches_one_at_a_time(judged):
  c = judged.case
  singles = [our_inputs(c, q) for q in judged.qpos]
  nbatch = len(singles)
  batch = predicates.GoalInputs(*(np.concatenate([getattr(s, f) for s in singles])
                                  for f in predicates.GoalInputs._fields))
  assert (predicates.satisfied(c.goal, batch) == judged.reference).all()
  # Contacts of several environments at once, each tagged by its environment (as MJX-Warp lists them).
  geoms, worlds = [], []
  for w, q in enumerate(judged.qpos):
    our_inputs(c, q)
    geoms.append(c.data.contact.geom.copy())
    worlds.append(np.full(c.data.ncon, w))
  touch = predicates.touching(c.goal, np.concatenate(geoms), np.concatenate(worlds), batch=nbatch)
  assert np.array_equal(touch, batch.touching)
  # The C batch lists no contacts: the engine's model counts them with touch sensors instead.
  sensed = scene.model(c.scene, sensors=predicates.touch_sensor_xml(c.scene, c.model))
  for name in ("body_pos", "geom_size", "geom_contype", "dof_damping", "actuator_gainprm", "nq", "nv", "ngeom"):
    assert np.array_equal(getattr(sensed, name), getattr(c.model, name)), name
  goal = predicates.compile_goal(c.scene, sensed)
  assert goal.groups == c.goal.groups and (len(goal.touch_sensors) > 0) == any(a.touch[0] >= 0 for a in goal.atoms)
  d = mujoco.MjData(sensed)
  for q, single in zip(judged.qpos, singles):
    d.qpos[:], d.qvel[:] = q, 0.0
    mujoco.mj_forward(sensed, d)
    assert np.array_equal(predicates.touching_from_sensors(goal, d.sensordata[None]), single.touching)
  assert batch.touching.any() or not len(goal.touch_sensors)  # the states include touching ones


@pytest.mark.sweep
@pytest.mark.parametrize("suite,index", SLOW, ids=[f"{s}-{i}" for s, i in SLOW])
def test_every_other_task_of_the_four_suites(suite, index):
  case = make_case(suite, index)
  try:
    check_init_state_parity(case)
    j = judge(case)
    print(suite, index, check_goal_agreement(j))
    check_wrong_predicates_are_caught(j)
  finally:
    case.env.close()

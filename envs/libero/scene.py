"""A LIBERO task's scene for our engine: the MJCF that LIBERO composes for it, built once through
LIBERO's own environment and cached on disk with what our engine reads from it.

Why not LIBERO's environment itself: it is one robosuite env per process, 7-12 s to build and
~100 ms a control step with cameras (docs/libero.md); our engine steps many copies of one
`mujoco.MjModel`. The model here is the reference's own, bit for bit:
- the MJCF is the string robosuite compiles (`env.env.model.get_xml()`), not `sim.model.get_xml()`,
  whose round trip through mj_saveLastXML rounds body poses (up to 5e-7 m);
- a LIBERO reset then moves the fixtures (cabinets, stoves, racks: their root body's pose, sampled
  in the BDDL's fixture region, and not part of the benchmark's init states) and recolours
  visualisation sites. We record those changes as overrides, from the reset that LIBERO's and
  OpenVLA's evaluations make first (`env.seed(0)`, then `env.reset()`: their trial 0), and
  check at build time that model + overrides equals the reference's model in every array.

The cache lives under $SKILLPLUG_CACHE/libero (default ~/.cache/skillplug/libero), in a folder
named for the installation it was built from (`installed.provenance`): the MJCF holds absolute
paths to the installed meshes and textures, so it is never committed. Files are written whole
(a temporary file, then a rename).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from pathlib import Path

import mujoco
import numpy as np

from envs.libero import controller, suites
from envs.libero.installed import libero_module, provenance

FORMAT = 3  # of the cached metadata; a change rebuilds every scene (2: the controller's parameters; 3: eef_body)
CAMERAS = ("agentview", "robot0_eye_in_hand")  # LIBERO's evaluation cameras
CAMERA_SIZE = 128  # LIBERO's default; the MJCF does not depend on it
FIXTURE_SEED = 0  # env.seed(0) then env.reset(), as LIBERO's evaluations start
_JOINT_TYPES = {int(mujoco.mjtJoint.mjJNT_FREE): "free", int(mujoco.mjtJoint.mjJNT_BALL): "ball",
                int(mujoco.mjtJoint.mjJNT_SLIDE): "slide", int(mujoco.mjtJoint.mjJNT_HINGE): "hinge"}


@dataclasses.dataclass(frozen=True)
class Scene:
  """A cached scene: its task, the MJCF file and the metadata (`describe`'s dict, JSON)."""
  task: suites.Task
  xml_path: Path
  meta: dict

  @property
  def nq(self) -> int:
    return self.meta["nq"]

  @property
  def nv(self) -> int:
    return self.meta["nv"]

  @property
  def goal(self) -> list:
    return self.meta["goal"]


def cache_root() -> Path:
  """Where scenes are cached: $SKILLPLUG_CACHE/libero, else ~/.cache/skillplug/libero."""
  base = os.environ.get("SKILLPLUG_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "skillplug")
  return Path(base) / "libero"


def _install_key() -> str:
  text = json.dumps({"format": FORMAT, **provenance()}, sort_keys=True)
  return hashlib.sha256(text.encode()).hexdigest()[:12]


def _paths(task: suites.Task, cache: Path | None) -> tuple[Path, Path]:
  folder = (cache or cache_root()) / _install_key() / task.suite
  stem = f"{task.index:02d}_{task.name}"
  return folder / f"{stem}.xml", folder / f"{stem}.json"


def _write_atomic(path: Path, text: str) -> None:
  path.parent.mkdir(parents=True, exist_ok=True)
  fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
  try:
    with os.fdopen(fd, "w") as f:
      f.write(text)
    os.replace(tmp, path)
  except BaseException:
    os.unlink(tmp)
    raise


def reference_env(suite: str, which: int | str, seed: int = FIXTURE_SEED, camera_size: int = CAMERA_SIZE):
  """LIBERO's own environment for a task (`OffScreenRenderEnv`, both evaluation cameras), seeded
  and reset as LIBERO's evaluations do before their first trial. The judge of our rebuild."""
  task = suites.task(suite, which)
  env_wrapper = libero_module("libero.libero.envs")
  env = env_wrapper.OffScreenRenderEnv(bddl_file_name=task.bddl_file, camera_names=list(CAMERAS),
                                       camera_heights=camera_size, camera_widths=camera_size)
  env.seed(seed)
  env.reset()
  return env


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, i: int) -> str:
  return mujoco.mj_id2name(model, kind, i)


def _joints(model: mujoco.MjModel, names) -> list[dict]:
  out = []
  for name in names:
    j = model.joint(name)
    out.append({"name": name, "type": _JOINT_TYPES[int(j.type[0])], "qposadr": int(j.qposadr[0]),
                "dofadr": int(j.dofadr[0])})
  return out


def _model_arrays(model: mujoco.MjModel) -> dict:
  out = {}
  for name in dir(model):
    if name.startswith("_"):
      continue
    try:
      value = getattr(model, name)
    except Exception:  # noqa: BLE001 - a property MuJoCo cannot produce for this model
      continue
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
      out[name] = value
  return out


def _apply_overrides(model: mujoco.MjModel, meta: dict) -> mujoco.MjModel:
  for body, pose in meta["body_overrides"].items():
    model.body(body).pos[:] = pose["pos"]
    model.body(body).quat[:] = pose["quat"]
  for site, rgba in meta["site_rgba_overrides"].items():
    model.site(site).rgba[:] = rgba
  return model


def describe(env, task: suites.Task) -> tuple[str, dict]:
  """The MJCF and the metadata of a reference env (`reference_env`): the reset's overrides, state
  sizes, the robot's joints and end-effector site, and for every object, fixture and region
  of the task the body, joints, contact geoms and LIBERO's parameters its predicates read."""
  inner = env.env
  xml = inner.model.get_xml()
  ours = mujoco.MjModel.from_xml_string(xml)
  ref = inner.sim.model._model
  bodies = [i for i in range(ref.nbody) if not (np.array_equal(ours.body_pos[i], ref.body_pos[i])
                                                and np.array_equal(ours.body_quat[i], ref.body_quat[i]))]
  sites = [i for i in range(ref.nsite) if not np.array_equal(ours.site_rgba[i], ref.site_rgba[i])]
  meta = {
    "body_overrides": {_name(ref, mujoco.mjtObj.mjOBJ_BODY, i): {"pos": ref.body_pos[i].tolist(),
                                                                  "quat": ref.body_quat[i].tolist()} for i in bodies},
    "site_rgba_overrides": {_name(ref, mujoco.mjtObj.mjOBJ_SITE, i): ref.site_rgba[i].tolist() for i in sites}}
  _apply_overrides(ours, meta)
  mine, theirs = _model_arrays(ours), _model_arrays(ref)
  differ = sorted(k for k in theirs if k not in mine or not np.array_equal(mine[k], theirs[k]))
  if differ:
    raise RuntimeError(f"{task.suite} task {task.index}: the reference model differs from the composed MJCF plus "
                       f"the reset's overrides in {', '.join(differ)}: LIBERO changed the model in a way scene.py "
                       "does not record")

  robot = inner.robots[0]
  objects, regions = {}, {}
  for name, state in inner.object_states_dict.items():
    obj = inner.get_object(name)
    if state.object_state_type == "site":
      regions[name] = {"class": type(obj).__name__, "parent": obj.parent_name, "joints": list(obj.joints or []),
                       "size": [float(v) for v in obj.size]}
      continue
    props = getattr(obj, "object_properties", {}) or {}
    objects[name] = {
      "kind": "fixture" if state.is_fixture else "object", "class": type(obj).__name__,
      "category": getattr(obj, "category_name", None), "body": obj.root_body,
      "joints": _joints(ours, obj.joints), "contact_geoms": sorted(obj.contact_geoms),
      "articulation": {k: [float(v) for v in r] for k, r in props.get("articulation", {}).items()} or None}
    missing = [g for g in objects[name]["contact_geoms"] if mujoco.mj_name2id(ours, mujoco.mjtObj.mjOBJ_GEOM, g) < 0]
    if missing:
      raise RuntimeError(f"{task.suite} task {task.index}: contact geoms of {name} not in the model: {missing}")
  parsed = inner.parsed_problem
  meta.update({
    "format": FORMAT, "suite": task.suite, "task_index": task.index, "task": task.name, "language": task.language,
    "bddl_file": os.path.normpath(task.bddl_file), "provenance": provenance(), "fixture_seed": FIXTURE_SEED,
    "cameras": list(CAMERAS), "control_freq": float(inner.control_freq), "timestep": float(ours.opt.timestep),
    "nq": int(ours.nq), "nv": int(ours.nv), "state_width": 1 + int(ours.nq) + int(ours.nv),
    "robot": {"eef_site": robot.controller.eef_name, "eef_body": robot.robot_model.eef_name, "arm_joints": _joints(ours, robot.robot_joints),
              "gripper_joints": _joints(ours, robot.gripper.joints),
              "init_qpos": [float(v) for v in robot.init_qpos]},
    "controller": controller.params_of(env),
    "objects": objects, "regions": regions,
    "obj_of_interest": list(parsed["obj_of_interest"]), "goal": [list(atom) for atom in parsed["goal_state"]]})
  return xml, meta


def build_scene(suite: str, which: int | str, cache: Path | None = None, env=None) -> Scene:
  """Build a task's scene through LIBERO's environment (7-12 s) and cache it; from `env` (a
  `reference_env` of the task, left open) when given, else from one made and closed here."""
  task = suites.task(suite, which)
  if env is not None:
    return _store(task, *describe(env, task), cache)
  env = reference_env(suite, task.index)
  try:
    xml, meta = describe(env, task)
  finally:
    env.close()
  return _store(task, xml, meta, cache)


def _store(task: suites.Task, xml: str, meta: dict, cache: Path | None) -> Scene:
  xml_path, meta_path = _paths(task, cache)
  meta = {**meta, "xml_sha256": hashlib.sha256(xml.encode()).hexdigest()}
  _write_atomic(xml_path, xml)
  _write_atomic(meta_path, json.dumps(meta, indent=1))  # last: its presence marks a whole scene
  return Scene(task, xml_path, meta)


def cached(suite: str, which: int | str, cache: Path | None = None) -> Scene | None:
  """The cached scene of a task, or None when there is none for this installation (or it is
  from another format, or its MJCF is not the one its metadata names)."""
  task = suites.task(suite, which)
  xml_path, meta_path = _paths(task, cache)
  try:
    meta = json.loads(meta_path.read_text())
    xml = xml_path.read_bytes()
  except (FileNotFoundError, json.JSONDecodeError):
    return None
  if meta.get("format") != FORMAT or meta.get("xml_sha256") != hashlib.sha256(xml).hexdigest():
    return None
  return Scene(task, xml_path, meta)


def scene(suite: str, which: int | str, cache: Path | None = None) -> Scene:
  """A task's scene: from the cache, or built through LIBERO's environment and cached."""
  return cached(suite, which, cache) or build_scene(suite, which, cache)


def model(s: Scene, sensors: str = "") -> mujoco.MjModel:
  """The scene's `MjModel` (mujoco 4.0.0; 0.2-0.3 s): the reference environment's model, bit for bit;
  with `sensors` (a <sensor> section: `predicates.touch_sensor_xml`) added, which changes
  nothing but the model's sensors."""
  xml = s.xml_path.read_text()
  if sensors:
    end = xml.rindex("</mujoco>")
    xml = xml[:end] + sensors + xml[end:]
  try:
    m = mujoco.MjModel.from_xml_string(xml)
  except ValueError as e:
    raise RuntimeError(f"the cached scene {s.xml_path} does not load (its asset paths point into the LIBERO "
                       f"installation it was built from; delete it to rebuild): {e}") from e
  return _apply_overrides(m, s.meta)


def split_states(states: np.ndarray, nq: int, nv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """(time, qpos, qvel) of LIBERO's flattened states [..., 1 + nq + nv] (robosuite's MjSimState
  layout, as the benchmark's init states hold them)."""
  states = np.asarray(states, dtype=np.float64)
  if states.shape[-1] != 1 + nq + nv:
    raise ValueError(f"a LIBERO state of this scene has 1 + nq + nv = {1 + nq + nv} numbers (time, qpos, qvel); "
                     f"got {states.shape[-1]}: an init state of another task?")
  return states[..., 0], states[..., 1:1 + nq], states[..., 1 + nq:]


def set_init_state(model: mujoco.MjModel, data: mujoco.MjData, state: np.ndarray) -> None:
  """Put `data` in a LIBERO state, as LIBERO's `set_init_state` does (time, qpos and qvel written,
  nothing else; then the forward pass)."""
  time, qpos, qvel = split_states(state, model.nq, model.nv)
  if np.ndim(time):
    raise ValueError(f"one state at a time, got states of shape {np.shape(state)}")
  data.time = float(time)
  data.qpos[:] = qpos
  data.qvel[:] = qvel
  mujoco.mj_forward(model, data)

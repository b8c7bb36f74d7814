"""A batch of one LIBERO task on MuJoCo's C engine (`mujoco.batch`), driven by LIBERO's actions.

B copies of a task's scene step together on a thread pool. Each control step (20 Hz) sets the
OSC goal from the 7-D actions, then runs the scene's 25 physics substeps one batched `mj_step`
at a time, with the controller's torques and the gripper's targets recomputed for the whole
batch between substeps from the arrays the engine returns (`envs.libero.controller`, numpy in
float64): what robosuite does for one env, for B at once and with no Python loop over them.

The batch is persistent: each simulation keeps its MjData, and every substep ends with the
position and velocity stages computed at the new state (`stage=mjSTAGE_VEL`), which the
controller reads and the next substep continues from.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import batch as mj_batch

from envs.libero import controller as osc
from envs.libero import predicates
from envs.libero import scene as scenes

ACTION_SIZE = 7  # LIBERO's: end-effector delta position (3), delta axis-angle (3), gripper (1)
_BOUND = ("qpos", "qvel", "ctrl", "time", "site_xpos", "site_xmat", "xpos", "xquat", "xmat", "xaxis",
          "xanchor", "M", "qfrc_bias", "sensordata")
# What robosuite's observations and LIBERO's _check_success read of positions and contacts after a
# step: MjData's derived fields after mj_step, which describe the state before its last substep.
_BEFORE_LAST = ("xpos", "xmat", "site_xpos", "site_xmat", "sensordata")
# What an observation reads: the pre-step kinematics of its substep (positions, images) ...
_OBSERVED = ("qpos", "xpos", "xquat", "site_xpos")
IMAGE_SIZE = 128  # LIBERO's default camera size
# How robosuite draws LIBERO's cameras: MuJoCo's default effects, 4x multisampling (the MJCF's),
# collision geoms (group 0) hidden, a scene of at most 1000 geoms.
_REFERENCE_LOOK = dict(flags_off=(), multisample=True, hidden_groups=(0,), max_geom=1000)


def _mass_index(model: mujoco.MjModel, dofs) -> np.ndarray:
  """[n, n] positions in MjData.M (CSR, lower triangle) of the joint-space inertia's block on `dofs`."""
  n = len(dofs)
  index = np.zeros((n, n), np.int64)
  for a, i in enumerate(dofs):
    for b, j in enumerate(dofs):
      row, col = max(i, j), min(i, j)
      start = model.M_rowadr[row]
      cols = model.M_colind[start:start + model.M_rownnz[row]]
      hit = np.flatnonzero(cols == col)
      if hit.size != 1:
        raise RuntimeError(f"dofs {row} and {col} have no shared entry in the mass matrix: not one kinematic chain")
      index[a, b] = start + hit[0]
  return index


class LiberoBatch:
  """`num_envs` copies of a LIBERO task's scene (`envs.libero.scene`), reset from benchmark init
  states and stepped with LIBERO actions [B, 7]; on `nthread` threads (0: every core). With
  `render=True`, `observe()` also draws LIBERO's two cameras (`image_size` square), as the
  reference renderer draws them, one renderer per thread (`render_processes=True`: per process,
  up to 18% faster on a CPU's software GL, docs/libero.md "Speed"); `multisample=False` draws them
  without the MJCF's 4x multisampling, 2.3x faster on a CPU's software GL, the edges a little harder."""

  def __init__(self, scene: scenes.Scene, num_envs: int, nthread: int = 0, render: bool = False,
               image_size: int = IMAGE_SIZE, multisample: bool = True, render_processes: bool = False):
    if "controller" not in scene.meta:
      raise ValueError(f"scene {scene.xml_path} has no controller parameters: built by an older scene.py")
    self.scene = scene
    self.model = scenes.model(scene, sensors=predicates.touch_sensor_xml(scene, scenes.model(scene)))
    self.goal = predicates.compile_goal(scene, self.model)
    self.num_envs = num_envs
    self.params = osc.params(scene.meta)
    self._batch = mj_batch.Batch(self.model, nsim=num_envs, nthread=nthread, persistent=True)
    self._a = {f: self._batch.bind(f) for f in _BOUND}
    joints = [self.model.joint(j["name"]).id for j in scene.meta["robot"]["arm_joints"]]
    if [int(self.model.jnt_dofadr[j]) for j in joints] != list(self.params.arm_dofs) or \
        any(self.model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE for j in joints):
      raise RuntimeError("the arm's joints are not the controller's hinge dofs")
    self._arm_joints = np.asarray(joints)
    self._mass = _mass_index(self.model, self.params.arm_dofs)
    self._control = None
    self._stale = None  # [B] bool: the controller still holds the reset pose's reading (controller.py)
    self._reset_arm = self._reset_pose_reading()
    self._objects = {name: self.model.body(o["body"]).id for name, o in scene.meta["objects"].items()
                     if o["kind"] == "object"}  # LIBERO observes its objects' poses, not its fixtures'
    self._gripper_qpos = [j["qposadr"] for j in scene.meta["robot"]["gripper_joints"]]
    self._eef_body = self.model.body(scene.meta["robot"]["eef_body"]).id
    self._cameras = None
    if render:
      from envs.mujoco_batch import CameraRenderer  # OpenGL only where images are asked for
      self._cameras = CameraRenderer(self.model, (image_size, image_size), self._batch.nthread,
                                     cameras=scenes.CAMERAS, processes=render_processes,
                                     **{**_REFERENCE_LOOK, "multisample": multisample})

  def _reset_pose_reading(self) -> osc.ArmState:
    """What robosuite's controller has cached when set_init_state returns: the robot at its reset pose
    (arm at `initial_joint`, fingers at their initial qpos, at rest). It depends on the robot's
    joints alone (the robot is its own kinematic tree), so the other joints stay at qpos0."""
    p = self.params
    d = mujoco.MjData(self.model)
    d.qpos[list(p.arm_qpos)] = p.initial_joint
    grip = [j["qposadr"] for j in self.scene.meta["robot"]["gripper_joints"]]
    d.qpos[grip] = p.gripper_init_qpos
    mujoco.mj_forward(self.model, d)
    return self._reading({f: getattr(d, f)[None] for f in _BOUND if f not in ("time", "ctrl")})

  def reset(self, states: np.ndarray) -> None:
    """Put environment i in LIBERO state `states[i]` (time, qpos, qvel; `suites.init_states`), as
    LIBERO's set_init_state after env.reset(): the controller's goal and gripper as a reset leaves them."""
    time, qpos, qvel = scenes.split_states(states, self.model.nq, self.model.nv)
    if qpos.shape[0] != self.num_envs:
      raise ValueError(f"got {qpos.shape[0]} states for {self.num_envs} environments")
    self._batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
    self._a["time"][:] = time
    self._a["qpos"][:] = qpos
    self._a["qvel"][:] = qvel
    self._batch.forward()
    self._control = osc.initial_state(self.params, self.num_envs)
    self._stale = np.ones(self.num_envs, bool)
    self._before_last = {f: self._a[f].copy() for f in _BEFORE_LAST}
    # robosuite's observation clock (Observable.update, one per env: all its observables share the
    # control rate): env.reset() and set_init_state each force a sample and advance it one model step.
    dt = float(self.model.opt.timestep)
    self._clock = np.full(self.num_envs, 0.0) + dt + dt
    self._sampled = np.ones(self.num_envs, bool)
    self._observed = {"now_qpos": self._a["qpos"].copy(), **{f: self._a[f].copy() for f in _OBSERVED}}

  def arm(self) -> osc.ArmState:
    """The controller's inputs at the current state."""
    return self._reading(self._a)

  def _controller_reading(self) -> osc.ArmState:
    """What robosuite's controller reads at the first substep of a control step: the current state,
    or the reset pose's cached reading in environments not stepped since their reset (all but the
    gravity and Coriolis compensation, which robosuite reads live)."""
    now = self.arm()
    if not self._stale.any():
      return now
    stale = self._stale
    pick = lambda cached, live: np.where(stale.reshape((-1,) + (1,) * (live.ndim - 1)), cached, live)  # noqa: E731
    return osc.ArmState(*(live if f == "bias" else pick(cached, live)
                          for f, cached, live in zip(osc.ArmState._fields, self._reset_arm, now)))

  def _reading(self, a: dict) -> osc.ArmState:
    p = self.params
    site_pos = a["site_xpos"][:, p.eef_site]
    axis, anchor = a["xaxis"][:, self._arm_joints], a["xanchor"][:, self._arm_joints]
    jacp = np.cross(axis, site_pos[:, None] - anchor)  # hinge j: axis_j x (site - anchor_j)
    jac = np.concatenate([np.swapaxes(jacp, 1, 2), np.swapaxes(axis, 1, 2)], axis=1)
    dofs = list(p.arm_dofs)
    return osc.ArmState(ee_pos=site_pos.copy(), ee_mat=a["site_xmat"][:, p.eef_site].reshape(-1, 3, 3),
                        jac=jac, mass=a["M"][:, self._mass], bias=a["qfrc_bias"][:, dofs],
                        q=a["qpos"][:, list(p.arm_qpos)], dq=a["qvel"][:, dofs])

  def step(self, actions: np.ndarray) -> None:
    """One control step of every environment: the goal from `actions` [B, 7], then the substeps."""
    actions = np.asarray(actions, np.float64)
    if actions.shape != (self.num_envs, ACTION_SIZE):
      raise ValueError(f"{self.scene.task.suite} task {self.scene.task.index}: actions have shape {actions.shape}, "
                       f"expected ({self.num_envs}, {ACTION_SIZE}) (LIBERO's delta pose + gripper)")
    if self._control is None:
      raise RuntimeError("step before reset")
    p = self.params
    reading = self._controller_reading()
    goal_pos, control = osc.set_goal(p, self._control, reading, actions)
    ctrl = self._a["ctrl"]
    arm_ids, grip_ids = list(p.arm_actuators), list(p.gripper_actuators)
    for k in range(p.substeps):
      ctrl[:, arm_ids] = osc.torques(p, goal_pos, control.goal_ori, reading if k == 0 else self.arm())
      ctrl[:, grip_ids], control = osc.gripper(p, control, actions[:, 6])
      if k == p.substeps - 1:
        self._before_last = {f: self._a[f].copy() for f in _BEFORE_LAST}
      sample, wrap = self._clock_tick()
      before = {f: self._a[f][sample] for f in _OBSERVED} if sample.any() else None  # copies only when sampled
      self._batch.step(nstep=1, stage=mujoco.mjtStage.mjSTAGE_VEL)
      if before is not None:
        self._observed["now_qpos"][sample] = self._a["qpos"][sample]
        for f in _OBSERVED:
          self._observed[f][sample] = before[f]
      self._sampled |= sample
      self._clock[wrap] %= 1.0 / self.scene.meta["control_freq"]
      self._sampled[wrap] = False
    self._control = control
    self._stale[:] = False

  def _clock_tick(self) -> tuple[np.ndarray, np.ndarray]:
    """robosuite's Observable.update after the coming substep, for every env's clock: (which envs
    sample then, which end a sampling period). The first update of a period samples (the joints
    after the substep; what MjData's derived fields describe after mj_step: the state before
    it); a period ends when the clock reaches 1 / control rate. Float for float as robosuite
    computes it (no observation delay): the phase of its samples inside a control step follows
    from it (for LIBERO after set_init_state, the 24th substep of 25)."""
    rate = 1.0 / self.scene.meta["control_freq"]
    self._clock += float(self.model.opt.timestep)
    sample = ~self._sampled & (rate >= self._clock)
    wrap = self._clock >= rate
    sample |= wrap & ~self._sampled  # robosuite's late sample (it warns)
    return sample, wrap

  def goal_inputs(self) -> predicates.GoalInputs:
    """The goal's inputs as LIBERO's _check_success reads them after a step: positions and contacts
    of the state before the last substep (MuJoCo's derived fields after mj_step), joints now."""
    b = self._before_last
    return predicates.GoalInputs(b["xpos"], b["xmat"], b["site_xpos"], b["site_xmat"], self._a["qpos"].copy(),
                                 predicates.touching_from_sensors(self.goal, b["sensordata"]))

  def observe(self, drawn: np.ndarray | None = None) -> dict:
    """LIBERO's observations of every environment, named as OffScreenRenderEnv names them and
    sampled when robosuite samples them (`_clock_tick`: after the 24th substep of a control step):
    joints at that moment, the end effector, the objects and the images from the state a substep
    earlier (what MjData's derived fields hold then). Quaternions are (x, y, z, w); robot0_eef_quat
    is the hand body's, robot0_eef_pos the grip site's, as robosuite has them. Images are
    upright ([B, H, W, 3] uint8): robosuite's are upside down (OpenGL's row order), which
    LIBERO's users flip. `drawn`: the environments whose images are drawn (default: all)."""
    b, p = self._observed, self.params
    site = p.eef_site
    obs = {"robot0_joint_pos": b["now_qpos"][:, list(p.arm_qpos)].copy(),
           "robot0_gripper_qpos": b["now_qpos"][:, self._gripper_qpos].copy(),
           "robot0_eef_pos": b["site_xpos"][:, site].copy(),  # robosuite: the grip site's position ...
           "robot0_eef_quat": b["xquat"][:, self._eef_body][:, [1, 2, 3, 0]].copy()}  # ... the hand body's orientation
    for name, body in self._objects.items():
      obs[f"{name}_pos"] = b["xpos"][:, body].copy()
      obs[f"{name}_quat"] = b["xquat"][:, body][:, [1, 2, 3, 0]].copy()
    if self._cameras is not None:
      images = self._cameras.render(b["qpos"], np.arange(self.num_envs) if drawn is None else np.asarray(drawn))
      obs.update({f"{c}_image": images[c] for c in scenes.CAMERAS})
    return obs

  def observed_qpos(self) -> np.ndarray:
    """[B, nq] every joint at the moment `observe()`'s joint observations were sampled."""
    return self._observed["now_qpos"].copy()

  def close(self) -> None:
    if self._cameras is not None:
      self._cameras.close()

  def success(self) -> np.ndarray:
    """[B] bool: the task's goal holds (LIBERO's _check_success after the last step or the reset)."""
    return predicates.satisfied(self.goal, self.goal_inputs())

  def goal_atoms(self) -> np.ndarray:
    """[B, atoms] bool: each atom of the goal (`predicates.atom_values`); the goal holds where all do."""
    return predicates.atom_values(self.goal, self.goal_inputs())

  @property
  def data(self) -> dict:
    """The bound arrays (live views, [B, ...]) of the batch: qpos, qvel, xpos, xquat, site_xpos, ..."""
    return self._a

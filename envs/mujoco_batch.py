"""The CPU backend: a batch of environments on MuJoCo's C engine (`mujoco.batch`).

Same API as `envs.batched.BatchedEnv` (reset(keys[B]) and step(state,
actions[B, 7]) return a batched Brax `State` with the same observations,
metrics, `done` and bookkeeping). The physics runs in C on a thread pool,
outside JAX; everything else is the task's own JAX code, jitted over the
batch: the reset sampler gives qpos, and the success predicate, observations
and episode bookkeeping (`TabletopEnv.next_state`, under Brax's own episode
and vmap wrappers) read the arrays the engine returns, as a `PhysicsState`
whose fields have mjx.Data's names. Episodes that have ended are not
simulated further.

The C batch holds the simulations' state, so `step` must be given the State
the previous `reset` or `step` returned.

Failure isolation: MuJoCo answers an unstable state (NaN or huge values in
qpos, qvel or qacc) with a warning and by resetting that simulation to the
model's defaults, which sets its clock to 0. Each simulation's clock starts at
`CLOCK_START`, so a reset shows as a clock behind the steps taken; that
episode, and one whose state is not finite, fails alone and keeps its last
good state, as a NaN does on MJX-Warp.
"""

from __future__ import annotations

import os
import queue
import subprocess
import threading
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import Env, State
from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper
from flax import struct
from mujoco import batch as mj_batch

from envs import appearance as appearances
from envs import render_process
from envs.env import SOLVER_LIMIT_BITS, TabletopEnv, clipped_ctrl
from envs.headless import RendererError, renderer_error
from envs.robot import CAMERAS

RENDERER = "mujoco-opengl"  # what datasets and runs record (MJX-Warp's is "warp-raycast")
# The integration state saved before each step, restored where a step fails.
SAVED_FIELDS = ("qpos", "qvel", "act", "ctrl", "qacc_warmstart", "time")
DERIVED_FIELDS = ("xpos", "xquat", "xmat", "site_xpos", "geom_xpos", "sensordata")
CLOCK_START = 1.0  # s; MuJoCo's reset of an unstable simulation sets it to 0
# Without a GPU, EGL renders with Mesa's llvmpipe, which gives every GL context
# a thread per core; our renderers already run one per core, and for 64x64
# images one llvmpipe thread each is 1.4x faster (GPU drivers ignore this).
os.environ.setdefault("LP_NUM_THREADS", "1")
# Effects MJX-Warp's ray caster does not draw either, off: about 10% faster.
_RENDER_FLAGS_OFF = ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX", "mjRND_FOG", "mjRND_HAZE")
# A GL context is made in milliseconds (EGL) to a second (OSMesa); one not
# made by then is stuck, and the caller is told rather than left waiting.
RENDERER_START_S = 60.0


@struct.dataclass
class PhysicsState:
  """What task logic reads of the physics, as float32 arrays named as in mjx.Data."""
  qpos: jax.Array
  qvel: jax.Array
  xpos: jax.Array
  xquat: jax.Array
  xmat: jax.Array  # [nbody, 3, 3]
  site_xpos: jax.Array
  geom_xpos: jax.Array
  sensordata: jax.Array
  time: jax.Array  # s since the reset
  overflow: jax.Array  # int32: SOLVER_LIMIT_BITS seen (the solver at its iteration limit)

  def where(self, cond, other: "PhysicsState") -> "PhysicsState":
    """`other` where `cond`, as mjx.Data.where."""
    return jax.tree.map(lambda mine, theirs: jnp.where(cond, theirs, mine), self, other)

  @property
  def shape(self):
    """Brax's EpisodeWrapper sizes its counters by its reset argument's
    shape[:-1], written for a PRNG key; a single environment's state is a
    scalar to it."""
    return self.qpos.shape[:-1] + (2,)


class _Bookkeeping(Env):
  """A task's State bookkeeping as a Brax Env whose 'action' is the physics'
  result, so that Brax's episode and vmap wrappers apply unchanged."""

  def __init__(self, env: TabletopEnv):
    self.env = env

  def reset(self, physics) -> State:
    return self.env.first_state(physics)

  def step(self, state: State, result) -> State:
    physics, failed, keep = result
    return self.env.next_state(state, physics, failed, keep)

  @property
  def observation_size(self):
    return self.env.observation_size

  @property
  def action_size(self) -> int:
    return self.env.action_size

  @property
  def backend(self) -> str:
    return self.env.backend


_clipped_ctrl = jax.jit(clipped_ctrl)
_BOOKKEEPING: dict = {}


def _jitted_bookkeeping(env: TabletopEnv):
  """(reset sampler, first State, next State), jitted over the batch. Shared by
  every batch of the same task class and config, so that evaluating run after
  run (a new environment batch per task and run) compiles them once."""
  key = (type(env), env.config)
  if key not in _BOOKKEEPING:
    wrapped = VmapWrapper(EpisodeWrapper(_Bookkeeping(env), env.episode_length, action_repeat=1))
    _BOOKKEEPING[key] = (jax.jit(jax.vmap(env.initial_qpos)), jax.jit(wrapped.reset), jax.jit(wrapped.step))
  return _BOOKKEEPING[key]


class MujocoBatchEnv:
  """`num_envs` copies of a task on MuJoCo's C engine, stepped on `nthread` threads (0: every core).

  With `render=True`, obs also holds `side_rgb` and `wrist_rgb` (uint8,
  [B, H, W, 3]) drawn by `mujoco.Renderer` (OpenGL; offscreen through EGL or
  OSMesa, as envs/headless.py picks MUJOCO_GL), one renderer per worker thread.
  A renderer that cannot start raises `envs.headless.RendererError` here.
  appearance="shifted" draws each environment in its own look (`envs.appearance`,
  from its reset key, kept in state.info["appearance"]); the physics is the same.
  """

  backend = "mujoco"
  devices = None

  def __init__(self, env: TabletopEnv, num_envs: int, render: bool = False, image_size=(64, 64),
               nthread: int = 0, appearance: str = "default"):
    if env.config.backend != "mujoco":
      raise ValueError(f"MujocoBatchEnv needs an environment made for the 'mujoco' backend, "
                       f"not {env.config.backend!r}")
    self.env = env
    self.num_envs = num_envs
    self.render = render
    self.image_size = tuple(image_size)
    self.renderer = RENDERER if render else None
    self.appearance = appearances.check(appearance)
    self._looks = appearances.looks_fn(env.mj_model) if render and appearance == "shifted" else None
    self._batch = mj_batch.Batch(env.mj_model, nsim=num_envs, nthread=nthread)
    self._saved = {f: self._batch.bind(f) for f in SAVED_FIELDS}
    self._derived = {f: self._batch.bind(f) for f in DERIVED_FIELDS + ("solver_niter",)}
    self._nbody = env.mj_model.nbody
    self._max_iter = env.mj_model.opt.iterations
    self._step_s = env.n_substeps * env.mj_model.opt.timestep
    self._initial, self._first, self._next = _jitted_bookkeeping(env)
    self._ctrl = _clipped_ctrl
    self._cameras = CameraRenderer(env.mj_model, self.image_size, self._batch.nthread) if render else None
    self._images = None
    self.render_s = 0.0  # wall seconds spent drawing the cameras so far (the rendering share, issue 29)

  @property
  def episode_length(self) -> int:
    return self.env.episode_length

  def reset(self, keys: jax.Array) -> State:
    if keys.shape[0] != self.num_envs:
      raise ValueError(f"got {keys.shape[0]} reset keys for {self.num_envs} environments")
    qpos, ctrl = jax.device_get(self._initial(keys))
    self._batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
    self._saved["qpos"][:] = qpos
    self._saved["ctrl"][:] = ctrl
    self._saved["time"][:] = CLOCK_START
    self._batch.forward()
    state = self._first(self._physics(np.zeros(self.num_envs, np.int32)))
    if self._looks is not None:
      state = state.replace(info={**state.info, "appearance": self._looks(keys)})
    return self._with_images(state, np.arange(self.num_envs))

  def step(self, state: State, actions: jax.Array) -> State:
    if actions.shape != (self.num_envs, self.env.action_size):
      raise ValueError(
          f"{self.env.name}: actions have shape {actions.shape}, expected "
          f"({self.num_envs}, {self.env.action_size})")
    alive = np.asarray(state.done) == 0
    ids = np.flatnonzero(alive)
    saved = {f: a.copy() for f, a in self._saved.items()}
    ctrl = np.asarray(self._ctrl(jnp.asarray(actions)), np.float64)
    self._saved["ctrl"][ids] = ctrl[ids]
    if ids.size:
      self._batch.step(ids=ids, nstep=self.env.n_substeps)
    q, v, clock = self._saved["qpos"], self._saved["qvel"], self._saved["time"]
    finite = np.isfinite(q).all(1) & np.isfinite(v).all(1)
    failed = alive & (~finite | (clock < saved["time"] + self._step_s - 1e-6))
    if failed.any():  # keep the last good state of those simulations
      for f, a in self._saved.items():
        a[failed] = saved[f][failed]
    limit = (self._derived["solver_niter"].reshape(self.num_envs, -1).max(1) >= self._max_iter) & alive
    overflow = np.where(limit, SOLVER_LIMIT_BITS["solver_iterations"], 0).astype(np.int32)
    obs = {k: v for k, v in state.obs.items() if not k.endswith("_rgb")}
    state = self._next(state.replace(obs=obs),
                       (self._physics(overflow), jnp.asarray(failed), jnp.asarray(~alive | failed)))
    return self._with_images(state, ids[~failed[ids]])

  def _physics(self, overflow: np.ndarray) -> PhysicsState:
    f32 = {k: np.asarray(v, np.float32) for k, v in self._derived.items() if k != "solver_niter"}
    return PhysicsState(qpos=self._saved["qpos"].astype(np.float32), qvel=self._saved["qvel"].astype(np.float32),
                        time=(self._saved["time"] - CLOCK_START).astype(np.float32),
                        xmat=f32.pop("xmat").reshape(self.num_envs, self._nbody, 3, 3),
                        overflow=overflow, **f32)

  def _with_images(self, state: State, ids: np.ndarray) -> State:
    """Draw the simulations `ids` anew; the others keep their last images."""
    if not self.render:
      return state
    t0 = time.perf_counter()
    looks = state.info.get("appearance")
    looks = None if looks is None else jax.device_get(looks)
    self._images = self._cameras.render(self._saved["qpos"], ids, self._images, looks)
    images = {f"{c}_rgb": jnp.asarray(self._images[c]) for c in CAMERAS}
    self.render_s += time.perf_counter() - t0
    return state.replace(obs={**state.obs, **images})


class CameraRenderer:
  """A batch of states seen by `cameras` (by default our tabletop's two), drawn by `mujoco.Renderer`
  on `nthread` worker threads, or with `processes=True` in as many worker processes
  (`envs.render_process`: on a CPU's software OpenGL, threads share the GIL for part of each draw).

  An OpenGL context belongs to the thread that made it, so each worker makes,
  uses and closes its own renderer (`render_process.Drawer`), on its own copy
  of the model (a look is written into it before each environment's draw);
  `close` (or garbage collection) asks the workers to do so. The offscreen
  buffer is the image size, without multisampling unless asked. The
  constructor waits until every worker has its renderer: one that cannot
  start (no display for GLFW, no EGL) raises RendererError here, naming the
  cause, and a worker that dies later makes `render` raise, so that nothing
  waits on a dead thread or process.
  """

  def __init__(self, model: mujoco.MjModel, image_size, nthread: int, cameras=CAMERAS,
               flags_off=_RENDER_FLAGS_OFF, multisample: bool = False, hidden_groups=(), max_geom: int = 10000,
               processes: bool = False):
    self._size = tuple(image_size)
    self.cameras = tuple(cameras)
    self.processes = processes
    # Drawer's arguments; each worker its own copy of the model, into which looks are written
    drawer_args = lambda: (render_process.render_model(model, *self._size, multisample), self._size,  # noqa: E731
                           self.cameras, tuple(flags_off), tuple(hidden_groups), max_geom, appearances.LOOK_FIELDS)
    self._jobs, self._threads, self._procs = [], [], []
    if processes:
      self._start_processes(max(1, nthread), drawer_args())  # pickled: a copy for each process
      return
    self._jobs = [queue.SimpleQueue() for _ in range(max(1, nthread))]
    started = queue.SimpleQueue()
    self._threads = [threading.Thread(target=_render_worker, args=(drawer_args(), jobs, started),
                                      daemon=True, name="mujoco-render")
                     for jobs in self._jobs]  # the workers hold no reference to self, so it can be collected
    # Under GLFW (MUJOCO_GL unset or glfw), one renderer first, then the others:
    # two of its contexts failing at once deadlock inside MuJoCo 4.0's GL
    # loader, where one failing alone raises. EGL and OSMesa start together.
    first = len(self._threads) if os.environ.get("MUJOCO_GL", "").lower() in ("egl", "osmesa") else 1
    self._start(self._threads[:first], started)
    self._start(self._threads[first:], started)

  def _start(self, threads: list, started: queue.SimpleQueue) -> None:
    """Start `threads`; raise RendererError, naming the cause, unless each has its renderer."""
    for t in threads:
      t.start()
    deadline = time.monotonic() + RENDERER_START_S
    try:
      errors = [e for e in (started.get(timeout=max(0.0, deadline - time.monotonic())) for _ in threads)
                if e is not None]
    except queue.Empty:
      self.close()
      raise renderer_error(None, f"did not start within {RENDERER_START_S:.0f} s") from None
    if errors:
      self.close()
      raise renderer_error(errors[0]) from errors[0]

  def _start_processes(self, n: int, drawer_args: tuple) -> None:
    """Start `n` render processes; raise RendererError, naming the cause, unless each has its renderer."""
    self._procs = [render_process.start(drawer_args) for _ in range(n)]
    deadline = time.monotonic() + RENDERER_START_S
    for proc, conn in self._procs:
      try:
        kind, detail = self._answer(proc, conn, deadline)
      except RendererError:
        self.close()
        raise
      if kind != "ready":
        self.close()
        raise renderer_error(RuntimeError(f"in a render process: {detail.strip()}"))

  def _answer(self, proc, conn, deadline: float | None = None):
    """A render process's next message; RendererError if it dies first or misses `deadline`."""
    while not conn.poll(1.0):
      if proc.poll() is not None:
        raise RendererError(f"a MuJoCo render process died without an answer (exit code {proc.returncode})")
      if deadline is not None and time.monotonic() > deadline:
        raise renderer_error(None, f"did not start within {RENDERER_START_S:.0f} s")
    try:
      return conn.recv()
    except EOFError:
      raise RendererError(f"a MuJoCo render process closed its socket (exit code {proc.poll()})") from None

  def render(self, qpos: np.ndarray, ids: np.ndarray, out: dict | None = None, looks: dict | None = None) -> dict:
    """Draw simulations `ids` (from their qpos rows) into `out` ({camera: [B, H, W, 3]}).

    looks: {field: [B, ...]} (`envs.appearance.LOOK_FIELDS`), row i the model's
    visual fields for simulation i; None draws the model as it is."""
    if out is None:
      out = {c: np.zeros((qpos.shape[0],) + self._size + (3,), np.uint8) for c in self.cameras}
    workers = len(self._procs) if self.processes else len(self._jobs)
    if not workers:
      raise RendererError("the renderer is closed")
    chunks = [c for c in np.array_split(np.asarray(ids), workers) if c.size]
    if self.processes:
      return self._render_in_processes(qpos, chunks, out, looks)
    done = queue.SimpleQueue()
    for jobs, chunk in zip(self._jobs, chunks):
      jobs.put((qpos, chunk, out, looks, done))
    errors = [e for e in (self._wait(done) for _ in chunks) if e is not None]
    if errors:
      raise errors[0]
    return out

  def _render_in_processes(self, qpos: np.ndarray, chunks: list, out: dict, looks: dict | None) -> dict:
    """Each process draws its chunk; after a failure the renderer closes (an unread answer would
    otherwise be taken for the next call's images)."""
    try:
      for (proc, conn), chunk in zip(self._procs, chunks):
        try:
          conn.send((np.ascontiguousarray(qpos[chunk]),
                     None if looks is None else {f: v[chunk] for f, v in looks.items()}))
        except OSError as e:
          raise RendererError(f"a MuJoCo render process died: its socket is closed (exit code {proc.poll()})") from e
      errors = []
      for (proc, conn), chunk in zip(self._procs, chunks):
        kind, detail = self._answer(proc, conn)
        if kind == "images":
          for c in self.cameras:
            out[c][chunk] = detail[c]
        else:
          errors.append(detail)
      if errors:
        raise RendererError(f"a MuJoCo render process failed: {errors[0].strip()}")
    except RendererError:
      self.close()
      raise
    return out

  def _wait(self, done: queue.SimpleQueue):
    """A worker's answer; RendererError if a worker thread is gone (it would never answer)."""
    while True:
      try:
        return done.get(timeout=1.0)
      except queue.Empty:
        if not all(t.is_alive() for t in self._threads):
          raise RendererError("a MuJoCo renderer thread died without an answer (see its traceback above)") from None

  def close(self) -> None:
    for jobs in getattr(self, "_jobs", ()):
      jobs.put(None)
    self._jobs = []
    procs, self._procs = getattr(self, "_procs", []), []
    for proc, conn in procs:
      try:
        conn.send(None)
      except (OSError, ValueError):  # its pipe is closed already
        pass
    for proc, conn in procs:
      try:
        proc.wait(timeout=10)
      except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
      conn.close()

  def __del__(self):
    self.close()


def _render_worker(drawer_args: tuple, jobs: queue.SimpleQueue, started: queue.SimpleQueue) -> None:
  """Make a Drawer and tell `started` (None, or the exception), then draw jobs until None."""
  try:
    drawer = render_process.Drawer(*drawer_args)
  except Exception as e:  # noqa: BLE001  handed to the caller's thread
    started.put(e)
    return
  started.put(None)
  try:
    while (job := jobs.get()) is not None:
      qpos, ids, out, looks, done = job
      try:
        drawer.draw(qpos, ids, out, looks)
        done.put(None)
      except Exception as e:  # noqa: BLE001  handed to the caller's thread
        done.put(e)
  finally:
    drawer.close()

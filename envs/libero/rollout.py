"""Closed-loop trials of a policy on a LIBERO task, batched on our engine, as LIBERO evaluates.

Trial i starts from the benchmark's init state i (`suites.init_states`), the arm is held still for
`suites.SETTLE_STEPS` no-op steps while the objects settle (LIBERO's evaluation scripts do the
same), then the policy acts for up to the suite's time limit. The policy is an
`envs.rollout.Controller`, as on DISCOVERSE: per control step one jitted call for the whole batch
reads `state.obs` (our LIBERO layout, `envs.libero.layout`: the fields a LIBERO dataset holds, the
two cameras at the controller's `image_size`, and the task's instruction as the word ids the
controller asks for, `Controller.instruction`) and returns LIBERO actions [B, 7], then one
batched step of the C engine. A policy trained on our LIBERO datasets runs here unchanged.

Two outcomes per trial, and how far it got:
- `libero_success`: LIBERO's own rule, the goal's predicate at any step within the limit (its
  evaluation ends the episode there: the field's published numbers count this);
- `success`, ours: the goal holds, and keeps holding for `HOLD_STEPS` consecutive steps (0.5 s)
  with the gripper commanded open and its fingers open (`RELEASED_GAP`), the first of them
  within the limit: placed and let go, not still held in the hand;
- `atoms_reached`: which atoms of the goal (LIBERO-10's are mostly two: both objects placed) held
  at some step within the limit, each on its own: the progress of a trial that fails.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from envs.libero import engine, layout, predicates, suites
from envs.libero import scene as scenes
from envs.libero.expert import HOLD_STEPS  # 0.5 s at 20 Hz: the experts' rule, and a policy's
from envs.rollout import Controller, _jitted
RELEASED_GAP = 0.075  # m between the Panda's fingers: open (0.078-0.080 when nothing is between them)
REST = np.array([0, 0, 0, 0, 0, 0, -1.0])  # LIBERO's no-op: hold the pose, gripper open


class State(NamedTuple):
  """What a controller reads (as `envs.rollout`'s Brax state): the observations, and `done`."""
  obs: dict
  done: jax.Array


class Trials(NamedTuple):
  success: np.ndarray  # [B] bool, ours: placed and released, held 0.5 s
  libero_success: np.ndarray  # [B] bool: LIBERO's predicate at some step within the limit
  first_success_step: np.ndarray  # [B] LIBERO's first success step (after settling), -1 if none
  declared_step: np.ndarray  # [B] the step our success was declared, -1 if none
  steps_run: int
  frames: list | None = None  # agentview [T_i + 1, H, W, 3] uint8 of the first trials: start to end
  queries: np.ndarray | None = None  # [B] policy queries made before the trial ended
  routing: np.ndarray | None = None  # [T, B, K] the router's weights at each query (NaN where none)
  atoms_reached: np.ndarray | None = None  # [B, atoms] bool: each atom of the goal held at some step within the limit
  atoms: tuple[str, ...] = ()  # the goal's atoms, as the BDDL writes them (`predicates.atom_name`)


def run_trials(name: str, controller: Controller, trials: int = suites.INIT_STATES_PER_TASK, first: int = 0,
               frames: int = 0, video_size: int = 128, nthread: int = 0) -> Trials:
  """Trials `first` .. `first + trials - 1` of LIBERO task `name` ("<suite>:<index>"), all at once.
  frames: also return the agentview camera of the first `frames` trials (at the controller's image
  size, or `video_size` for a state policy)."""
  task = suites.parse(name)
  if first < 0 or trials < 1 or first + trials > suites.INIT_STATES_PER_TASK:
    raise ValueError(f"{name}: trials {first}..{first + trials - 1}: the benchmark has init states "
                     f"0..{suites.INIT_STATES_PER_TASK - 1}")
  if frames > trials:
    raise ValueError(f"frames={frames} > trials={trials}")
  s = scenes.scene(task.suite, task.index)
  layout.check_fits(s.meta)
  size = controller.image_size
  if size is not None and size[0] != size[1]:
    raise ValueError(f"LIBERO's cameras are square; this controller reads {size[0]}x{size[1]} images")
  render = size is not None or frames > 0
  batch = engine.LiberoBatch(s, trials, nthread=nthread, render=render,
                             image_size=size[0] if size is not None else video_size)
  try:
    return _loop(batch, task, controller, suites.init_states(task.suite, task.index)[first:first + trials], frames)
  finally:
    batch.close()


def _observe(batch: engine.LiberoBatch, cameras: bool, frames: int) -> tuple[dict, dict]:
  """The controller's observations (with the cameras if it reads them) and LIBERO's (images of
  every env, or of the first `frames` only when the controller reads none)."""
  raw = batch.observe(None if cameras else np.arange(frames))
  obs = layout.observation(batch.scene.meta, raw, batch.observed_qpos())
  if cameras:
    for ours, theirs in zip(layout.CAMERAS, scenes.CAMERAS):
      obs[f"{ours}_rgb"] = raw[f"{theirs}_image"]
  return obs, raw


def _loop(batch: engine.LiberoBatch, task: suites.Task, controller: Controller, states: np.ndarray,
          frames: int) -> Trials:
  n, limit = batch.num_envs, task.time_limit
  batch.reset(states)
  rest = np.tile(REST, (n, 1))
  for _ in range(suites.SETTLE_STEPS):
    batch.step(rest)
  cameras = controller.image_size is not None
  obs, raw = _observe(batch, cameras, frames)
  video = [raw[f"{scenes.CAMERAS[0]}_image"][:frames]] if frames else []
  done = np.zeros(n, bool)
  words = ({} if controller.instruction is None
           else {"instruction": np.tile(controller.instruction(task.language), (n, 1))})
  state = State({k: jnp.asarray(v) for k, v in {**obs, **words}.items()}, jnp.asarray(done))
  act, w = _jitted(controller.act), controller.weights
  cstate = _jitted(controller.init)(state)
  first = np.full(n, -1)
  reached = np.zeros((n, len(batch.goal.atoms)), bool)
  declared = np.full(n, -1)
  held = np.zeros(n, np.int64)
  queries = np.zeros(n, np.int32)
  k = controller.num_skills
  routing = np.full((limit + HOLD_STEPS, n, max(k, 1)), np.nan, np.float32) if k else None
  t = 0
  while t < limit + HOLD_STEPS - 1 and not done.all():
    actions, cstate, info = act(w, cstate, state, t)
    actions = np.asarray(actions, np.float64)
    queried = np.asarray(info.get("queried", np.ones(n, bool))) & ~done & (t < limit)
    queries += queried
    if k and "routing" in info:
      routing[t] = np.where(queried[:, None], np.asarray(info["routing"], np.float32), np.nan)
    if t >= limit:  # past the limit only a hold already under way may finish: the arm rests
      actions = rest
    batch.step(actions)
    atoms = batch.goal_atoms()
    ok = atoms.all(axis=-1)
    reached |= atoms & (t < limit)
    obs, raw = _observe(batch, cameras, frames)
    gap = obs["gripper_qpos"][:, 0] - obs["gripper_qpos"][:, 1]
    first[(first < 0) & ok & (t < limit)] = t
    released = ok & (actions[:, 6] < 0) & (gap >= RELEASED_GAP)
    held = np.where(released & ((held > 0) | (t < limit)), held + 1, 0)
    newly = (declared < 0) & (held >= HOLD_STEPS)
    declared[newly] = t
    done |= newly | ((t >= limit - 1) & (held == 0))  # nothing left to decide
    if frames:
      video.append(raw[f"{scenes.CAMERAS[0]}_image"][:frames])
    state = State({k: jnp.asarray(v) for k, v in {**obs, **words}.items()}, jnp.asarray(done))
    t += 1
  clip = None
  if frames:
    stack = np.stack(video)
    ends = np.where(declared >= 0, declared + 1, t)
    clip = [stack[:ends[i] + 1, i] for i in range(frames)]
  return Trials(success=declared >= 0, libero_success=first >= 0, first_success_step=first,
                declared_step=declared, steps_run=t, frames=clip, queries=queries,
                routing=routing[:t] if routing is not None else None, atoms_reached=reached,
                atoms=tuple(predicates.atom_name(a) for a in batch.goal.atoms))

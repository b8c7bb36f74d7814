"""A toy problem where skills are needed: a 2-D point robot with a gripper.

The fast screen (and regression test) for the skill library (issue 27): four
ground-truth behaviour primitives are shared across tasks and selected by
what the observation shows, so a library that works should find them, and
the routing can be scored against the known primitive label of every step.

World: the robot at (x, y) in [-1, 1]^2, a binary gripper g (0 at reset),
three landmarks A, B, C at seeded random positions at least
`min_separation` apart. Primitives: reach A, reach B, reach C, toggle (close
the gripper: command g = 1 until it switches; every task toggles at most
once, so "toggle" always ends closed). A task is a sequence of 2-3
primitives; the unseen (few-shot) tasks recombine the seen ones' primitives
in new orders, each primitive at a place in the sequence where some seen task
has it (so every input a frozen encoder reads on an unseen task was set in
pretraining; only the combination is new).

Observation, shaped like the tabletop tasks' so `Policy` reads it unchanged
(use_images=False, joint_dim=3, action_dim=3): joint_pos = [x, y, g];
object_state in slots of 7 numbers, as the tabletop tasks' object poses are
(so `model.object_tokens=per_object` gives one token per landmark): one slot
per landmark [x, y, 0...], then the task as its program (for each place in
the sequence, a one-hot over the four primitives, zeros past the task's
end) and the stage one-hot, zero-padded to whole slots. The current
primitive is the program's entry at the stage, both shown. (A first version
showed a task one-hot: the unseen tasks' bits were never set in pretraining,
so few-shot adaptation with the encoder frozen could not see which task it
was; docs/measurements/skill_library.md.)
Action = absolute target [x, y, g]: the robot moves towards (x, y) by at
most `max_step` per control step; the gripper switches once the command
(g > 0.5) has differed from it for `toggle_steps` consecutive steps.

Stages: a reach completes within `reach_radius` of its landmark, a toggle
when the gripper has switched during its stage; the last stage must hold
its condition `hold_steps` steps. Stages advance one at a time, so reaching
the last landmark with a stage skipped does nothing. Success: every stage
done within `time_limit` control steps.

Everything is a pure function of one environment's `State`; batches are
`jax.vmap` of them and a rollout is one `lax.scan` (`rollout`).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

PRIMITIVES = ("reach_A", "reach_B", "reach_C", "toggle")
TOGGLE = 3
_SYMBOL = "ABCT"

# Seen (multi-task) and unseen (few-shot) tasks: sequences of primitive ids.
SEEN_TASKS = ((0, 1), (1, 2), (2, 0), (0, 3, 1), (1, 3, 2), (2, 3, 0))
UNSEEN_TASKS = ((1, 0), (0, 3, 2), (2, 1, 0))  # B>A, A>T>C, C>B>A
TASKS = SEEN_TASKS + UNSEEN_TASKS
MAX_STAGES = max(len(t) for t in TASKS)
NUM_TASKS = len(TASKS)
SEEN = tuple(range(len(SEEN_TASKS)))
UNSEEN = tuple(range(len(SEEN_TASKS), NUM_TASKS))

JOINT_DIM = 3
ACTION_DIM = 3
SLOT = 7  # numbers per object slot (a tabletop object's position and quaternion)
_PROGRAM_WIDTH = MAX_STAGES * len(PRIMITIVES)
_INFO_SLOTS = -(-(_PROGRAM_WIDTH + MAX_STAGES) // SLOT)
OBJECT_STATE_DIM = SLOT * (3 + _INFO_SLOTS)
PROGRAM_BITS = slice(3 * SLOT, 3 * SLOT + _PROGRAM_WIDTH)  # where object_state shows the task's program
STAGE_BITS = slice(PROGRAM_BITS.stop, PROGRAM_BITS.stop + MAX_STAGES)  # and the stage

# [tasks, MAX_STAGES] primitive ids, -1 past a task's end; [tasks] lengths.
TASK_TABLE = np.array([t + (-1,) * (MAX_STAGES - len(t)) for t in TASKS], np.int32)
TASK_LENGTH = np.array([len(t) for t in TASKS], np.int32)


def task_name(task: int) -> str:
  """'A>T>B' style names: the primitive sequence."""
  return ">".join(_SYMBOL[p] for p in TASKS[task])


# The tasks as the experiment pipeline names them (file-safe: a run's folder is named by its task),
# and its tasksets: the seen tasks (multi-task training) and the unseen ones (few-shot).
TASKSET = "toy_skills"
FEWSHOT_TASKSET = "toy_skills_fewshot"


def task_id(task: int) -> str:
  """'toy_ATB' style: the task's name in results and folders (`task_name` is its table heading)."""
  return "toy_" + "".join(_SYMBOL[p] for p in TASKS[task])


TASKSETS = {TASKSET: tuple(task_id(t) for t in SEEN), FEWSHOT_TASKSET: tuple(task_id(t) for t in UNSEEN)}
TASK_IDS = {task_id(t): t for t in range(NUM_TASKS)}


@dataclasses.dataclass(frozen=True)
class ToySkillsConfig:
  # 0.1, not 0.05: at 0.05 the quick-size ACT (3000 steps) reached 43% with a held-out position
  # L1 of 0.04, so the screen measured regression precision, not which primitive was chosen.
  reach_radius: float = 0.1
  max_step: float = 0.1  # per control step, in the units of [-1, 1]^2
  toggle_steps: int = 3  # consecutive commanded steps before the gripper switches
  hold_steps: int = 3  # the last stage's condition must hold this long
  time_limit: int = 80  # control steps (three far reaches need ~70)
  landmark_range: float = 0.8  # landmarks in [-r, r]^2
  start_range: float = 0.9  # robot starts in [-r, r]^2
  min_separation: float = 0.4  # between landmarks
  candidates: int = 32  # landmark draws tried per reset (rejection sampling)


class State(NamedTuple):
  pos: jax.Array  # [2]
  grip: jax.Array  # [] float32, 0 open / 1 closed
  landmarks: jax.Array  # [3, 2]
  task: jax.Array  # [] int32
  stage: jax.Array  # [] int32, == task length once done
  hold: jax.Array  # [] int32, steps the current stage's condition has held
  grip_count: jax.Array  # [] int32, consecutive steps the command has differed from grip
  stage_grip: jax.Array  # [] float32, the gripper when the stage began
  t: jax.Array  # [] int32, control steps taken
  success: jax.Array  # [] bool, latched at the step every stage is done


def _landmarks(cfg: ToySkillsConfig, key) -> jax.Array:
  """Three landmarks at least `min_separation` apart: the first of `candidates` draws that is
  (all draws fail with negligible probability at the defaults; the last is then used)."""
  draws = jax.random.uniform(key, (cfg.candidates, 3, 2), minval=-cfg.landmark_range,
                             maxval=cfg.landmark_range)
  d = jnp.linalg.norm(draws[:, :, None] - draws[:, None], axis=-1) + 1e9 * jnp.eye(3)
  ok = d.min(axis=(1, 2)) >= cfg.min_separation
  return draws[jnp.where(ok.any(), jnp.argmax(ok), cfg.candidates - 1)]


def reset(cfg: ToySkillsConfig, key, task) -> State:
  k_land, k_pos = jax.random.split(key)
  f, i = jnp.float32, jnp.int32
  return State(
      pos=jax.random.uniform(k_pos, (2,), minval=-cfg.start_range, maxval=cfg.start_range),
      grip=jnp.zeros((), f), landmarks=_landmarks(cfg, k_land), task=jnp.asarray(task, i),
      stage=jnp.zeros((), i), hold=jnp.zeros((), i), grip_count=jnp.zeros((), i),
      stage_grip=jnp.zeros((), f), t=jnp.zeros((), i), success=jnp.zeros((), bool))


def num_stages(state: State) -> jax.Array:
  return jnp.asarray(TASK_LENGTH)[state.task]


def primitive(state: State) -> jax.Array:
  """The current stage's primitive id; -1 once every stage is done."""
  table = jnp.asarray(TASK_TABLE)
  return jnp.where(state.stage < num_stages(state),
                   table[state.task, jnp.minimum(state.stage, MAX_STAGES - 1)], -1)


def observe(state: State) -> dict:
  """The policy's view: joint_pos [3], object_state [OBJECT_STATE_DIM] (no stage bit once done)."""
  slots = jnp.pad(state.landmarks, ((0, 0), (0, SLOT - 2))).reshape(-1)
  program = jax.nn.one_hot(jnp.asarray(TASK_TABLE)[state.task], len(PRIMITIVES)).reshape(-1)  # -1: zeros
  info = jnp.concatenate([program,
                          jax.nn.one_hot(state.stage, MAX_STAGES) * (state.stage < num_stages(state))])
  obj = jnp.concatenate([slots, jnp.pad(info, (0, OBJECT_STATE_DIM - slots.shape[0] - info.shape[0]))])
  return {"joint_pos": jnp.concatenate([state.pos, state.grip[None]]),
          "object_state": obj.astype(jnp.float32)}


def _stage_condition(cfg: ToySkillsConfig, state: State) -> jax.Array:
  prim = primitive(state)
  near = jnp.linalg.norm(state.pos - state.landmarks[jnp.clip(prim, 0, 2)]) < cfg.reach_radius
  return jnp.where(prim == TOGGLE, state.grip != state.stage_grip, near) & (prim >= 0)


def step(cfg: ToySkillsConfig, state: State, action) -> State:
  """Move, actuate the gripper, then advance the stage if its condition has held long enough."""
  action = jnp.asarray(action, jnp.float32)
  delta = action[:2] - state.pos
  dist = jnp.linalg.norm(delta)
  delta = delta * jnp.minimum(1.0, cfg.max_step / jnp.maximum(dist, 1e-9))
  pos = jnp.clip(state.pos + delta, -1.0, 1.0)
  command = (action[2] > 0.5).astype(jnp.float32)
  count = jnp.where(command != state.grip, state.grip_count + 1, 0)
  flip = count >= cfg.toggle_steps
  grip = jnp.where(flip, 1.0 - state.grip, state.grip)
  state = state._replace(pos=pos, grip=grip, grip_count=jnp.where(flip, 0, count), t=state.t + 1)

  holds = _stage_condition(cfg, state)
  hold = jnp.where(holds, state.hold + 1, 0)
  n = num_stages(state)
  need = jnp.where(state.stage == n - 1, cfg.hold_steps, 1)
  advance = holds & (hold >= need)
  stage = state.stage + advance
  return state._replace(stage=stage, hold=jnp.where(advance, 0, hold),
                        stage_grip=jnp.where(advance, grip, state.stage_grip),
                        success=state.success | (stage >= n))


def success(state: State) -> jax.Array:
  return state.success


def expert(state: State) -> jax.Array:
  """The scripted expert's action [3] (privileged: it reads the state, not the observation).

  Reach: the landmark as target, the gripper as it is. Toggle: stay, command the
  gripper opposite to where the stage began. Done: stay.
  """
  prim = primitive(state)
  target = jnp.where(prim >= 0, state.landmarks[jnp.clip(prim, 0, 2)], state.pos)
  target = jnp.where(prim == TOGGLE, state.pos, target)
  grip = jnp.where(prim == TOGGLE, 1.0 - state.stage_grip, state.grip)
  return jnp.concatenate([target, grip[None]])


class Trajectory(NamedTuple):
  """Every control step of a batch, step t what the controller saw and sent: [B, T, ...]."""
  obs: dict  # joint_pos [B, T, 3], object_state [B, T, D]
  action: jax.Array  # [B, T, 3]
  label: jax.Array  # [B, T] the primitive being executed (-1 once done)
  active: jax.Array  # [B, T] bool: the task was not yet done when the step began
  info: dict  # whatever the controller returned per step, [B, T, ...]


def reset_batch(cfg: ToySkillsConfig, key, tasks) -> State:
  """One environment per entry of `tasks` [B], each with its own start."""
  tasks = jnp.asarray(tasks, jnp.int32)
  keys = jax.random.split(key, tasks.shape[0])
  return jax.vmap(lambda k, task: reset(cfg, k, task))(keys, tasks)


def rollout(cfg: ToySkillsConfig, controller: Callable, carry, state: State, steps: int | None = None):
  """Drive a batch for `steps` control steps (default: the time limit) in one `lax.scan`.

  controller(carry, state, t) -> (actions [B, 3], carry, info dict of [B, ...]); a learned
  policy reads only `observe(state)`, the expert the state. Returns (final state, Trajectory).
  Episodes keep running after success (it is latched), so every column has the same length.
  """
  steps = cfg.time_limit if steps is None else steps
  vstep = jax.vmap(lambda s, a: step(cfg, s, a))

  def body(c, t):
    carry, state = c
    action, carry, info = controller(carry, state, t)
    record = (jax.vmap(observe)(state), action, jax.vmap(primitive)(state), ~state.success, info)
    return (carry, vstep(state, action)), record

  (_, final), (obs, action, label, active, info) = jax.lax.scan(
      body, (carry, state), jnp.arange(steps))
  swap = lambda x: jnp.swapaxes(x, 0, 1)
  return final, Trajectory(*jax.tree.map(swap, (obs, action, label, active, info)))


def expert_controller(carry, state: State, t):
  del t
  return jax.vmap(expert)(state), carry, {}


def demonstrations(cfg: ToySkillsConfig, key, tasks) -> tuple[State, Trajectory]:
  """Expert episodes, one per entry of `tasks` [B]: the steps to keep are `traj.active`."""
  return rollout(cfg, expert_controller, (), reset_batch(cfg, key, tasks))

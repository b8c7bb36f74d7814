"""Skill labels mined from the demonstrations themselves (ours, not the paper's): no annotation.

Issue 27 found that the skill library routes and its skills specialise once the
router is told a partition of the steps into primitives (the toy's oracle), and
that nothing in the paper's objective finds that partition. These labellers
propose one from signals every demonstration already holds: what the gripper
is commanded to do and what in the scene moves. The router is then trained to
predict the label (`loss.router_label`, batches' `skill_label`), which needs no
label at evaluation: the router reads only the observation.

Each labeller is a pure numpy function of one episode's arrays ([T, ...]) and
returns int32 labels [T] in [0, K) for a library of K = 4 skills.

tabletop_phases (the DISCOVERSE-style tasks): the phase of a manipulation.
  0 free motion  gripper commanded open, nothing moving (reach, retreat)
  1 grasp        gripper commanded closed, nothing moving yet
  2 transport    something in the scene moves within the next `window` steps
                 (a carried object, a pushed one, a drawer or lid joint)
  3 release      gripper commanded open just after a transport ended (let go, back off)
toy_targets (envs/toy_skills.py): the landmark the commanded target is nearest
  to (0-2), or 3 while the gripper command differs from the gripper. On the toy
  this equals the primitive label by construction of its expert (its reaches
  aim at the landmark, its toggle holds still): the toy shows what the library
  does with a mined partition, not that mining is hard there.
"""

from __future__ import annotations

import numpy as np

LABELLERS = ("tabletop_phases", "toy_targets")
PHASES = ("free_motion", "grasp", "transport", "release")


def tabletop_phases(joint_pos: np.ndarray, object_state: np.ndarray, action: np.ndarray, *,
                    window: int = 5, moved: float = 0.01, closed: float = 0.01,
                    after: int = 15) -> np.ndarray:
  """Phase labels of one tabletop episode (module docstring).

  joint_pos [T, 7], object_state [T, D] (object poses and scene joints, any padding
  constant), action [T, 7] (last: the commanded gripper opening, m). A step is in transport
  when some object-state entry changes by more than `moved` between it and `window` steps
  later (the episode's last step past its end); otherwise in grasp while the gripper is
  commanded closed (below `closed` m); otherwise in release for `after` steps once a
  transport has ended; otherwise in free motion. `joint_pos` is not read: the command, not
  the fingers' lag, marks the phase.
  """
  del joint_pos
  t = np.arange(len(action))
  ahead = np.minimum(t + window, len(action) - 1)
  moving = np.abs(object_state[ahead] - object_state).max(-1) > moved
  last_moving = np.maximum.accumulate(np.where(moving, t, -after - 1))
  labels = np.zeros(len(action), np.int32)
  labels[t - last_moving <= after] = 3
  labels[action[:, -1] < closed] = 1
  labels[moving] = 2
  return labels


def toy_targets(joint_pos: np.ndarray, object_state: np.ndarray, action: np.ndarray, *,
                landmarks: int = 3, slot: int = 7) -> np.ndarray:
  """Toy labels (module docstring): joint_pos [T, 3] = (x, y, gripper), action [T, 3] = target
  (x, y, gripper command), object_state [T, D] with landmark j's (x, y) at slot j."""
  marks = object_state[:, :landmarks * slot].reshape(len(action), landmarks, slot)[..., :2]
  nearest = np.linalg.norm(marks - action[:, None, :2], axis=-1).argmin(-1)
  toggling = (action[:, 2] > 0.5) != (joint_pos[:, 2] > 0.5)
  return np.where(toggling, landmarks, nearest).astype(np.int32)


def label_steps(labeller: str, joint_pos: np.ndarray, object_state: np.ndarray, action: np.ndarray,
                start: np.ndarray, length: np.ndarray) -> np.ndarray:
  """Labels of every step of a flat dataset (episode e: rows start[e] .. start[e] + length[e])."""
  if labeller not in LABELLERS:
    raise ValueError(f"unknown skill labeller {labeller!r}; known: {', '.join(LABELLERS)}")
  fn = tabletop_phases if labeller == "tabletop_phases" else toy_targets
  labels = np.full(len(action), -1, np.int32)
  for s, n in zip(np.asarray(start), np.asarray(length)):
    rows = slice(int(s), int(s) + int(n))
    labels[rows] = fn(joint_pos[rows], object_state[rows], action[rows])
  return labels

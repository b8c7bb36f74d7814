"""What a LIBERO demonstration or policy observes, in our datasets' names and widths.

Proprioception as LIBERO observes it (`engine.LiberoBatch.observe`): the arm's 7 joints, the two
finger joints, the end effector's position and quaternion (x, y, z, w). Object state, privileged
(LIBERO's own observations hold every movable object's pose but no fixture's joints): slot i of
`OBJECT_SLOTS` is the scene's i-th movable object (its position and quaternion, 7 numbers), then
the fixtures' joints (drawers, doors, knobs) in the scene's order, zero-padded to fixed widths so
that one policy reads every task of the four suites (8 objects and 4 fixture joints at most).
The cameras keep LIBERO's names, as its datasets do: agentview and eye_in_hand.

Importing this module loads neither LIBERO nor MuJoCo. The names and widths that configs check
are in `envs.names`.
"""

from __future__ import annotations

import numpy as np

from envs.names import LIBERO_CAMERAS, LIBERO_PROPRIO

OBJECT_SLOTS = 8  # LIBERO-10's widest scenes have 8 movable objects
JOINT_SLOTS = 8  # fixture joints (LIBERO-Spatial's cabinet and stove: 4)
OBJECT_STATE_DIM = 7 * OBJECT_SLOTS + JOINT_SLOTS
PROPRIO = LIBERO_PROPRIO
STATE = PROPRIO + (("object_state", OBJECT_STATE_DIM),)
CAMERAS = LIBERO_CAMERAS  # the dataset's names of scene.CAMERAS, in that order
_OBSERVED = {"joint_pos": "robot0_joint_pos", "gripper_qpos": "robot0_gripper_qpos", "eef_pos": "robot0_eef_pos",
             "eef_quat": "robot0_eef_quat"}


def tabletop_gripper(action: np.ndarray) -> np.ndarray:
  """LIBERO actions with the gripper command (-1 open, +1 close) read as our tabletop's commanded
  opening in metres (0 closed, 0.04 open), so that the labellers of data/segments.py, written for
  our tabletop's actions, mine LIBERO's demonstrations too."""
  out = np.array(action, np.float32, copy=True)
  out[..., -1] = np.where(out[..., -1] > 0, 0.0, 0.04)
  return out


def movable_objects(meta: dict) -> list[str]:
  return [name for name, o in meta["objects"].items() if o["kind"] == "object"]


def fixture_joints(meta: dict) -> list[int]:
  """qpos addresses of the fixtures' joints, in the scene's order."""
  return [j["qposadr"] for o in meta["objects"].values() if o["kind"] == "fixture" for j in o["joints"]]


def check_fits(meta: dict) -> None:
  objects, joints = movable_objects(meta), fixture_joints(meta)
  if len(objects) > OBJECT_SLOTS or len(joints) > JOINT_SLOTS:
    raise ValueError(f"{meta['suite']} task {meta['task_index']} has {len(objects)} movable objects and "
                     f"{len(joints)} fixture joints; the LIBERO object state holds {OBJECT_SLOTS} and {JOINT_SLOTS}")


def observation(meta: dict, obs: dict, qpos: np.ndarray) -> dict:
  """Our dataset's low-dim observation [B, width] per field from LIBERO's observations `obs`
  (`LiberoBatch.observe`) and the joints `qpos` [B, nq] sampled with them."""
  check_fits(meta)
  out = {ours: np.asarray(obs[theirs], np.float32) for ours, theirs in _OBSERVED.items()}
  b = len(out["joint_pos"])
  state = np.zeros((b, OBJECT_STATE_DIM), np.float32)
  for i, name in enumerate(movable_objects(meta)):
    state[:, 7 * i:7 * i + 3] = obs[f"{name}_pos"]
    state[:, 7 * i + 3:7 * i + 7] = obs[f"{name}_quat"]
  joints = fixture_joints(meta)
  state[:, 7 * OBJECT_SLOTS:7 * OBJECT_SLOTS + len(joints)] = qpos[:, joints]
  out["object_state"] = state
  return out

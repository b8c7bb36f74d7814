"""What the cameras see in the default and the shifted appearance (ours, issue 29), as one PNG.

    python -m figures.appearance_pictures --task stack_block --trials 4 --out /tmp/appearance.png

A row per evaluation trial (the starts of `skillplug eval --seed SEED`), four
columns: side camera default, side shifted, wrist default, wrist shifted. The
images are the policy's own (the backend's renderer, at --size pixels), drawn
at the start of each trial.
"""

from __future__ import annotations

import argparse

import envs  # first: it picks MUJOCO_GL (envs/headless.py) before mujoco is imported

import imageio.v3 as iio  # noqa: E402
import numpy as np  # noqa: E402

from envs import rollout  # noqa: E402
from envs.appearance import APPEARANCES  # noqa: E402
from envs.robot import CAMERAS  # noqa: E402
from skillplug_jax.evaluate.protocol import EVAL_SEED  # noqa: E402


def appearance_grid(task: str, trials: int, seed: int = EVAL_SEED, size: int = 128,
                    backend: str = "mujoco") -> np.ndarray:
  """[trials * size, 4 * size, 3] uint8: per trial, side and wrist cameras, default then shifted."""
  keys = rollout.reset_keys(seed, trials)
  seen = {}
  for appearance in APPEARANCES:
    benv = envs.make(task, num_envs=trials, render=True, image_size=(size, size), backend=backend,
                     appearance=appearance)
    obs = benv.reset(keys).obs
    seen[appearance] = {cam: np.asarray(obs[f"{cam}_rgb"]) for cam in CAMERAS}
  columns = [seen[a][cam] for cam in CAMERAS for a in APPEARANCES]
  return np.concatenate([np.concatenate([c[i] for c in columns], axis=1) for i in range(trials)], axis=0)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", required=True, help="the PNG to write")
  p.add_argument("--task", default="stack_block")
  p.add_argument("--trials", type=int, default=4)
  p.add_argument("--seed", type=int, default=EVAL_SEED, help="evaluation seed: trial i starts from reset_keys(seed)[i]")
  p.add_argument("--size", type=int, default=128, help="square camera images, pixels")
  p.add_argument("--backend", default="mujoco", choices=("mujoco", "mjx-warp"))
  args = p.parse_args(argv)
  iio.imwrite(args.out, appearance_grid(args.task, args.trials, args.seed, args.size, args.backend))
  print(f"wrote {args.out}: rows are trials {args.seed}/0..{args.trials - 1}; columns side default, "
        "side shifted, wrist default, wrist shifted")


if __name__ == "__main__":
  main()

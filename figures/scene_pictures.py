"""Side-camera pictures of every task's initial scene (docs/scenes/*.png).

    make scenes        # or: python -m figures.scene_pictures --out docs/scenes

The initial state comes from the task's own reset (seed 0, MJX-Warp); the
picture is drawn with MuJoCo's OpenGL renderer (offscreen, envs/headless.py), at a
higher resolution than the policy's images.
"""

from __future__ import annotations

import argparse
import os

import envs  # first: it picks MUJOCO_GL (envs/headless.py) before mujoco is imported

import imageio.v3 as iio  # noqa: E402
import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs import rollout  # noqa: E402


def initial_qpos(name: str, seed: int = 0) -> np.ndarray:
  env = envs.make(name, num_envs=1)
  state = jax.jit(env.reset)(rollout.reset_keys(seed, 1))
  return np.asarray(state.pipeline_state.qpos[0]), env.env.mj_model


def picture(model, qpos, camera="side", size=(480, 360)) -> np.ndarray:
  data = mujoco.MjData(model)
  data.qpos[:] = qpos
  mujoco.mj_forward(model, data)
  with mujoco.Renderer(model, height=size[1], width=size[0]) as r:
    r.update_scene(data, camera=camera)
    return r.render()


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", default="docs/scenes")
  p.add_argument("--seed", type=int, default=0)
  args = p.parse_args(argv)
  os.makedirs(args.out, exist_ok=True)
  tiles = []
  for name in envs.TASKS:
    qpos, model = initial_qpos(name, args.seed)
    img = picture(model, qpos)
    iio.imwrite(os.path.join(args.out, f"{name}.png"), img)
    tiles.append(picture(model, qpos, size=(240, 180)))
    print(f"wrote {args.out}/{name}.png")
  tiles.append(np.full_like(tiles[0], 255))
  rows = [np.concatenate(tiles[i:i + 4], axis=1) for i in range(0, 12, 4)]
  iio.imwrite(os.path.join(args.out, "all_tasks.png"), np.concatenate(rows, axis=0))
  print(f"wrote {args.out}/all_tasks.png")


if __name__ == "__main__":
  main()

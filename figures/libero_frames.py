"""One frame per LIBERO suite, ours beside the reference renderer's (docs/scenes/libero_*.png: libero_spatial.png, ...).

    python -m figures.libero_frames --out docs/scenes        # part of `make scenes`

For one task per suite (the default tasks of tests/test_libero_engine.py) at its benchmark
init state 0: LIBERO's two cameras at 128x128 as OffScreenRenderEnv draws them (flipped
upright: robosuite's rows are bottom-up) and as our batch draws them (`engine.LiberoBatch`,
render=True), with their absolute difference x10. Writes a PNG per suite and libero_frames.json
with the difference per camera.
"""

from __future__ import annotations

import argparse
import json
import os

import envs  # noqa: F401  first: it picks MUJOCO_GL (envs/headless.py) before mujoco is imported

import imageio.v3 as iio  # noqa: E402
import numpy as np  # noqa: E402

from envs.libero import engine, scene, suites  # noqa: E402

TASKS = (("libero_spatial", 4), ("libero_object", 0), ("libero_goal", 5), ("libero_10", 2))


def frames(suite: str, index: int, state: int = 0) -> dict:
  """{camera: (reference upright, ours)} at one init state."""
  states = suites.init_states(suite, index)[[state]]
  env = scene.reference_env(suite, index)
  try:
    s = scene.cached(suite, index) or scene.build_scene(suite, index, env=env)
    ref = env.set_init_state(states[0])
  finally:
    env.close()
  batch = engine.LiberoBatch(s, 1, nthread=1, render=True)
  try:
    batch.reset(states)
    ours = batch.observe()
  finally:
    batch.close()
  return {cam: (np.asarray(ref[f"{cam}_image"])[::-1], ours[f"{cam}_image"][0]) for cam in scene.CAMERAS}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--out", default="docs/scenes")
  args = parser.parse_args()
  os.makedirs(args.out, exist_ok=True)
  report = {}
  for suite, index in TASKS:
    rows, report[suite] = [], {"task": suites.task(suite, index).name, "init_state": 0}
    for cam, (ref, ours) in frames(suite, index).items():
      diff = np.abs(ref.astype(int) - ours)
      report[suite][cam] = {"max_abs_diff": int(diff.max()), "mean_abs_diff": float(diff.mean())}
      rows.append(np.concatenate([ref, ours, np.clip(diff * 10, 0, 255).astype(np.uint8)], axis=1))
    path = os.path.join(args.out, f"{suite}.png")
    iio.imwrite(path, np.concatenate(rows, axis=0))
    print(f"{path}: reference | ours | |difference| x10; {report[suite]}")
  with open(os.path.join(args.out, "libero_frames.json"), "w") as f:
    json.dump(report, f, indent=1)


if __name__ == "__main__":
  main()

"""make libero-cpu-image   (python -m experiments.pipeline --config libero_cpu_image --out results/libero_cpu_image)

`libero_cpu` (its arms, demonstrations, seeds and few-shot step) with the
paper's modality: both cameras (agentview, eye in hand) at 64x64 through the
`cpu_image` backbone (a small ResNet with GroupNorm, stem width 16, three
stages of one block: sized by measurement on DISCOVERSE, not searched on
LIBERO), beside LIBERO's proprioception and the instruction; 20 paired
trials per task (the benchmark's init states 0-19, the same for every arm;
LIBERO's protocol has 50: the CPU budget). Not yet run, for its cost on this
CPU. Measured 2026-12-07 (docs/measurements/libero.md): one 64x64 LIBERO
camera image costs about 38 ms of software GL on the 2-core VM (the scenes'
meshes, not the pixels, set it), so the 500 demonstrations of one suite take
about 4 hours and one policy's 500 trials of LIBERO-10 about 3.

Run one arm at a time with `make libero-cpu-image VARIANTS=long` (it resumes).
"""

import dataclasses
from pathlib import Path

from skillplug_jax.experiment import Experiment, load


def get_config() -> Experiment:
  exp = load("libero_cpu", Path(__file__).parent)
  model = dataclasses.replace(exp.train.model, use_images=True, cameras=("agentview", "eye_in_hand"),
                              image_size=(64, 64), backbone_width=16, backbone_stages=(1, 1, 1))
  train = dataclasses.replace(exp.train, preset="libero_cpu_image", model=model)
  return dataclasses.replace(exp, train=train, trials=20, eval_batch=20)

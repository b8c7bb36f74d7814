"""python -m experiments.pipeline --config skill_library_image --variants NAMES --out results/skill_library_image --publish docs/results/skill_library_image/<date>

Issue 27's state-only finalist in the paper's modality (issue 29): the `cpu_image`
preset (both cameras 64x64, the small ResNet) with the router trained, beside
the paper's four terms, to predict each step's manipulation phase mined from
the demonstrations (ours; data/segments.py tabletop_phases: free motion, grasp,
transport, release). Read beside the committed image protocol
(docs/results/paper_cpu_image/2026-12-05_3seeds/summary.json: ACT and the
paper's configuration, seeds 0-2), whose datasets it shares (the same
demonstrations; the labels are computed from them at load).

  phases_w01  the phase term at weight 0.1 (the state-only finalist: level with ACT over
              5 seeds with a token per object, routing by phase; a token per object has
              no meaning for an image policy, which reads no object state)
  phases      the phase term at weight 1 (state-only, seed 0: routing by phase, but 22-27
              points below ACT)
"""

import dataclasses
from pathlib import Path

from skillplug_jax.experiment import Experiment, Variant, load


def get_config() -> Experiment:
  return dataclasses.replace(
      load("cpu_image", Path(__file__).parent), policies=("skillplug",), seeds=(0,),
      reference="docs/results/paper_cpu_image/2026-12-05_3seeds/summary.json",
      variants=(
          Variant("phases_w01", ("train.loss.router_label=0.1", "train.skill_labels=tabletop_phases"),
                  "router on mined phases at weight 0.1 (ours)"),
          Variant("phases", ("train.loss.router_label=1.0", "train.skill_labels=tabletop_phases"),
                  "router on mined phases at weight 1 (ours)"),
      ))

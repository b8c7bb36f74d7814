"""make k-sweep   (python -m experiments.pipeline --config k_sweep --out results/k_sweep --publish docs/results/k_sweep)

The number of skills, K in {2, 4, 6, 8}, at CPU scale: ACT+SkillPlug trained
as in the `cpu` config with K skills, evaluated on discoverse7 (multi-task
only, as the paper's K table). As in the paper, each K is one seed (seed 0);
K=4 is the `cpu` run, read with its 3 seeds from
docs/results/paper_cpu/summary.json, beside ACT. The skills' similarity per K
comes from `python -m experiments.skill_probes --config k_sweep --geometry-only`.
"""

import dataclasses
from pathlib import Path

from skillplug_jax.experiment import Experiment, Variant, load


def get_config() -> Experiment:
  return dataclasses.replace(
      load("cpu", Path(__file__).parent), policies=("skillplug",), seeds=(0,), run_fewshot=False,
      reference="docs/results/paper_cpu/summary.json",
      variants=tuple(Variant(f"k{k}", (f"train.model.plug.num_skills={k}",), f"K={k}") for k in (2, 6, 8)))

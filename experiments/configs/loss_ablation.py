"""make loss-ablation   (python -m experiments.pipeline --config loss_ablation --out results/loss_ablation --publish docs/results/loss_ablation)

The paper's loss-term ablation at CPU scale: ACT+SkillPlug trained as in the
`cpu` config with its objective built up one term at a time (Rec, +KL, +SD;
ACT's CVAE KL stays in every variant, as it is ACT's own loss), each variant
pretrained on discoverse7, evaluated, and adapted to the 4 unseen tasks. As
in the paper, the ablated variants are single-seed diagnostics (seed 0) and
the full objective (+BSA) is read with its 3 seeds from the `cpu` run
(docs/results/paper_cpu/summary.json), beside ACT. `--set seeds=0,1,2`
gives every variant 3 seeds (each variant-seed took 48-50 min of one core
here, pretraining, evaluation and few-shot, beside other work).
"""

import dataclasses
from pathlib import Path

from skillplug_jax.experiment import Experiment, Variant, load


def get_config() -> Experiment:
  return dataclasses.replace(
      load("cpu", Path(__file__).parent), policies=("skillplug",), seeds=(0,),
      reference="docs/results/paper_cpu/summary.json",
      variants=(Variant("rec", ("train.loss.kl=0", "train.loss.sd=0", "train.loss.bsa=0"), "Rec"),
                Variant("kl", ("train.loss.sd=0", "train.loss.bsa=0"), "+KL"),
                Variant("sd", ("train.loss.bsa=0",), "+SD")))

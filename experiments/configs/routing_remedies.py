"""python -m experiments.pipeline --config routing_remedies --out results/routing_remedies --publish docs/results/routing_remedies

Remedies for the degenerate skill library measured on the `cpu` runs
(docs/results/paper_cpu/skill_probes.md: routing near uniform on every task,
uniform weights as good as the router's, the K interactor outputs in two
opposite groups of copies, mean cosine -1/(K-1), that the uniform mixture
cancels; docs/results/k_sweep/skill_probes.md). Each
variant changes one thing the paper's text leaves open, and is screened by
closed-loop multi-task success on seed 0 against the `cpu` run (read from
docs/results/paper_cpu/summary.json); the one worth it gets more seeds
(`--variants NAME --set seeds=0,1,2`):

  temp0.1   router softmax temperature 0.1 (the same logits, sharper weights)
  film      the FiLM interactor instead of query-offset attention
  sd0.01    lambda_SD 0.01 instead of 0.1 (less pull towards the cancelling geometry)

The loss ablation (loss_ablation.py: +KL has no SD at all) is the fourth.
"""

import dataclasses

from experiments.configs import Experiment, Variant, cpu


def get_config() -> Experiment:
  return dataclasses.replace(
      cpu.get_config(), policies=("skillplug",), seeds=(0,), run_fewshot=False,
      reference="docs/results/paper_cpu/summary.json",
      variants=(Variant("temp0.1", ("train.model.router_temperature=0.1",), "router T=0.1"),
                Variant("film", ("train.model.interactor=film",), "FiLM interactor"),
                Variant("sd0.01", ("train.loss.sd=0.01",), "lambda_SD=0.01")))

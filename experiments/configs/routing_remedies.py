"""python -m experiments.pipeline --config routing_remedies --out results/routing_remedies --publish docs/results/routing_remedies

Remedies for the degenerate skill library measured on the `cpu` runs
(docs/results/paper_cpu/skill_probes.md: routing near uniform on every task,
uniform weights as good as the router's, the K interactor outputs in two
opposite groups of copies, mean cosine -1/(K-1), that the uniform mixture
cancels; docs/results/k_sweep/skill_probes.md). Each
variant changes one thing the paper's text leaves open, and is screened by
closed-loop multi-task success on seed 0 against the `cpu` run (read from
docs/results/paper_cpu/summary.json); the one that changed the routing
(film) runs seeds 0, 1, 2 (its variant sets them):

  temp0.1   router softmax temperature 0.1 (the same logits, sharper weights)
  film      the FiLM interactor instead of query-offset attention
  sd0.01    lambda_SD 0.01 instead of 0.1 (less pull towards the cancelling geometry)

The loss ablation (loss_ablation.py: +KL has no SD at all) is the fourth.

Measured (2026-12-02, 2-core CPU, docs/results/routing_remedies/, docs/measurements/paper_protocol_cpu.md):
multi-task Avg. temp0.1 61.1 and sd0.01 64.6 (seed 0, routing entropy 0.97
and 0.99 of log 4, the same cancelling geometry); film 67.2 +- 4.1 over
seeds 0-2 against 64.7 +- 4.1 (query offset) and ACT's 70.4 +- 2.9, with the
router settled on one skill for every task (entropy 0.18; skill 0, 1 or 2
by seed), the other skills failing alone (film_probes/). None is a remedy:
film trades skills that cancel for one skill that does everything.
"""

import dataclasses
from pathlib import Path

from skillplug_jax.experiment import Experiment, Variant, load


def get_config() -> Experiment:
  return dataclasses.replace(
      load("cpu", Path(__file__).parent), policies=("skillplug",), seeds=(0,), run_fewshot=False,
      reference="docs/results/paper_cpu/summary.json",
      variants=(Variant("temp0.1", ("train.model.plug.router_temperature=0.1",), "router T=0.1"),
                Variant("film", ("train.model.plug.interactor=film", "seeds=0,1,2"), "FiLM interactor"),
                Variant("sd0.01", ("train.loss.sd=0.01",), "lambda_SD=0.01")))

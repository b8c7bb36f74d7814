"""The CPU quickstart: the whole SkillPlug pipeline, small, end to end.

    make quickstart      # or: python -m experiments.quickstart --out results/quickstart

The `quick` config (experiments/configs/quick.py) through the pipeline
(experiments/pipeline.py):

1. expert demonstrations (state only, 10 per task) of the 7 `discoverse7`
   tasks and of the 4 unseen `discoverse_fewshot4` tasks, as RLDS datasets;
2. multi-task pretraining of ACT and ACT+SkillPlug at the `quick` preset;
3. closed-loop evaluation of both on the 7 pretraining tasks (paired trials);
4. few-shot adaptation of both to each unseen task, then its evaluation;
5. the tables (success rate, policy queries per successful episode, and the
   same over paired trials), printed and written beside the runs.

The physics runs on the `auto` backend (MuJoCo's C engine on a CPU). Stages
2-4 run as two processes, one per policy: the physics and the quick networks
keep about one core busy each, so the two cores of a laptop-class CPU finish
both in the time of the slower one.

Every stage reuses what an earlier (or killed) run left: finished datasets,
checkpoints and evaluations are not redone. The numbers are a tiny-budget
smoke result, not the paper's protocol (see `make paper-cpu`).
"""

from __future__ import annotations

import sys

from experiments import pipeline


def main(argv=None) -> int:
  return pipeline.main(argv, default_config="quick", default_out="results/quickstart")


if __name__ == "__main__":
  sys.exit(main())

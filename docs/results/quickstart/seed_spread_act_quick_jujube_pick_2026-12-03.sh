#!/bin/bash
# ACT, quick preset, seeds 0, 7, 8: jujube_pick over 50 paired trials (issue 26's seed-spread claim).
set -e
export MUJOCO_GL=egl GLIBC_TUNABLES=glibc.malloc.hugetlb=1
for s in 0 7 8; do
  .venv/bin/skillplug pretrain --taskset discoverse7 --policy act --config quick --seed $s --set workdir=results/seedcheck/runs/act_quick_seed$s
done
.venv/bin/skillplug eval --runs 'results/seedcheck/runs/act_quick_seed{seed}' --seeds 0,7,8 --taskset jujube_pick --trials 50 --out results/seedcheck/eval_jujube_pick

#!/bin/bash
# The cpu_image preset search (issue 29): one candidate = train ACT (seed 0, discoverse7, 100 demos,
# both cameras 64x64) on one core, then evaluate it on 50 paired trials per task on the same core.
# usage: commands.sh CORE NAME overrides...     (overrides: --set values on the cpu_image config)
# e.g.   commands.sh 0 w16_s111_8k model.backbone_width=16 model.backbone_stages=1,1,1 max_steps=8000
core=$1; name=$2; shift 2
sets=""; for o in "$@"; do sets="$sets --set $o"; done
cd "$(dirname "$0")/../../.."
mkdir -p results/cpu_image_search
start=$(date +%s)
taskset -c "$core" .venv/bin/skillplug pretrain --taskset discoverse7 --policy act --preset cpu_image --seed 0 \
  --workdir "results/cpu_image_search/$name" $sets --set data_dir=results/datasets --backend mujoco \
  > "results/cpu_image_search/$name.train.log" 2>&1 || exit 1
mid=$(date +%s)
taskset -c "$core" .venv/bin/skillplug eval --runs "results/cpu_image_search/$name" --taskset discoverse7 \
  --trials 50 --out "results/cpu_image_search/${name}_eval" > "results/cpu_image_search/$name.eval.log" 2>&1 || exit 2
end=$(date +%s)
echo "$name train_s=$((mid-start)) eval_s=$((end-mid)) $*" >> results/cpu_image_search/times.txt

#!/bin/bash
# usage: cand.sh CORE NAME overrides...
core=$1; name=$2; shift 2
sets=""; for o in "$@"; do sets="$sets --set $o"; done
cd /work/main
start=$(date +%s)
taskset -c $core .venv/bin/skillplug pretrain --taskset discoverse7 --policy act --preset quick --seed 0 --workdir results/cpu_search/$name $sets --set lr_schedule=cosine --set data_dir=results/datasets > /tmp/p13/$name.train.log 2>&1
mid=$(date +%s)
taskset -c $core .venv/bin/skillplug eval --runs results/cpu_search/$name --taskset discoverse7 --trials 50 --out results/cpu_search/${name}_eval > /tmp/p13/$name.eval.log 2>&1
end=$(date +%s)
echo "$name train_s=$((mid-start)) eval_s=$((end-mid))" >> /tmp/p13/cand_times.txt

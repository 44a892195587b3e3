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
SHARED := stages/__init__.py stages/artifacts.py stages/errors.py stages/provenance.py stages/se3.py stages/tol.py

.PHONY: help install demo test lint bench benchmark analysis sample plan mpc execute reproduce golden clean

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
$(B)/analysis/analysis.json: $(SCENE_FILE) $(wildcard data/objects/*) stages/analyze.py stages/meshfile.py stages/scene.py $(SHARED) | $(INSTALLED)
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

# A plan variant (VARIANT=no-regrasp, no-tumble or no-usp: the paper's ablations) shares the graph;
# its plan, trajectories and execution go to $(B)/<variant>/ (the full planner: $(B)/full/).
VARIANT ?=
R := $(B)/$(if $(VARIANT),$(VARIANT),full)
PLAN_FLAGS := $(if $(VARIANT),--$(VARIANT),)

PLAN_CODE := stages/plan.py stages/diagnosis.py stages/transit.py stages/connect.py stages/trajectory.py $(GRAPH_CODE)
# pivot plan exits 1 when no plan exists; plan.json still records why, so Make keeps it.
$(R)/plan.json: $(B)/graph/graph.json $(PLAN_CODE) $(SHARED) | $(INSTALLED)
	$(PIVOT) plan $(SCENE_FILE) --build $(B) --out $@ $(PLAN_FLAGS) || [ $$? -eq 1 ]

$(R)/plan.png: $(R)/plan.json stages/plots.py | $(INSTALLED)
	$(PIVOT) show plan $(B) --scene $(SCENE_FILE) --plan $< --png $@

plan: $(R)/plan.png ## build the graph, plan with backtracking and draw the plan (Fig. 10b)

$(R)/trajectories.parquet: $(R)/plan.json $(PLAN_CODE) $(SHARED) | $(INSTALLED)
	$(PIVOT) mpc $(SCENE_FILE) --build $(B) --plan $< --out $@

$(R)/trajectories.png: $(R)/trajectories.parquet stages/plots.py | $(INSTALLED)
	$(PIVOT) show trajectories $< --scene $(SCENE_FILE) --png $@

mpc: $(R)/trajectories.png ## MPC force and joint trajectories of the plan, drawn (Fig. 12)

SEED ?= 0
# pivot execute exits 1 when the object misses the goal in physics; execution.json records how.
$(R)/execution.json: $(R)/trajectories.parquet stages/execute.py $(SHARED) | $(INSTALLED)
	$(PIVOT) execute $(SCENE_FILE) --build $(B) --trajectories $< --out $(R) --seed $(SEED) || [ $$? -eq 1 ]

$(R)/execution.png: $(R)/execution.json | $(INSTALLED)
	$(PIVOT) show execution $(R) --scene $(SCENE_FILE) --png $@

execute: $(R)/execution.png ## run the trajectories in PyBullet physics, storyboard + GIF (Fig. 15-18)

# ------------------------------------------------------------------------------------------ jobs
demo: $(INSTALLED) ## the whole chain on the default scene, in physics: summary, figures and a GIF
	$(PIVOT) run $(SCENE_FILE)

SCENES := default exp1_reach exp2_rotate exp3_obstacle
# Every scene with the full planner and the three ablations, two scenes at a time (2 cores); an
# ablation with no plan (as the paper reports) or a failed execution is recorded in its artifacts,
# not a reason to stop.
# A variant whose plan has the same steps as the full planner's gets the full planner's trajectories
# and execution (the same steps and seed give byte-identical ones) instead of running them again.
reproduce: $(INSTALLED) ## all experiment scenes, full planner and ablations, in physics -> build/report/README.md
	printf '%s\n' $(SCENES) | xargs -P 2 -I{} $(SHELL) -c 'for v in "" no-regrasp no-tumble no-usp; do \
	  b=build/{}; $(MAKE) --no-print-directory -s SCENE={} VARIANT=$$v plan > /dev/null 2>&1 || true; \
	  if [ -n "$$v" ] && [ -f $$b/full/execution.json ] && \
	     $(PIVOT) diff $$b/full/plan.json $$b/$$v/plan.json --only steps > /dev/null 2>&1; then \
	    for f in trajectories.parquet trajectories.json trajectories.png execution.parquet execution.json \
	             execution.png execution.gif frames.npz; do [ ! -f $$b/full/$$f ] || cp $$b/full/$$f $$b/$$v/; done; \
	    continue; fi; \
	  $(MAKE) --no-print-directory -s -k SCENE={} VARIANT=$$v mpc execute > /dev/null 2>&1 || echo "{} $${v:-full}: stopped"; \
	  done; echo "{}: done"'
	$(PIVOT) report build --out build/report/README.md

# The standard benchmark: every object family x 6 goals, 2 physics seeds, on a Dask LocalCluster of 2
# workers. The suite is redrawn only when its code changes; `pivot benchmark run` skips the cases
# whose results are current, so an interrupted sweep resumes.
BENCH := build/benchmark
$(BENCH)/suite.json: stages/benchmark/suite.py stages/objects.py stages/sample.py stages/analyze.py \
		data/scenes/default.json $(SHARED) | $(INSTALLED)
	$(PIVOT) benchmark make $(BENCH) --goals 6 --seed 0

benchmark: $(BENCH)/suite.json ## general objects and goals swept on Dask -> build/benchmark/report.md
	$(PIVOT) benchmark run $(BENCH) --seeds 2 --workers 2 --timeout 600
	$(PIVOT) benchmark report $(BENCH)

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

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
# Code every stage uses (the benchmark suite's prerequisites; the stages' come from `pivot deps`).
SHARED := stages/__init__.py stages/artifacts.py stages/errors.py stages/provenance.py stages/se3.py stages/tol.py

.PHONY: help install lock demo test lint bench benchmark analysis sample plan mpc execute view browser reproduce \
	golden clean

help: ## list the targets
	@grep -E '^[a-z][a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'
	@echo "  (SCENE=name picks data/scenes/name.json; default: $(SCENE))"

$(INSTALLED): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[dev]'
	touch $@

install: $(INSTALLED) ## create .venv and install pivot with its dev tools (versions from constraints.txt)

# The newest versions pip resolves for pivot[dev] in a fresh venv, pinned; review the diff, then make test.
lock: ## refresh constraints.txt (the pinned versions make install and CI use)
	rm -rf build/lock
	$(PYTHON) -m venv build/lock
	build/lock/bin/python -m pip install -q '.[dev]'
	{ head -n 2 constraints.txt; build/lock/bin/python -m pip freeze --exclude-editable | grep -v '^pivot=='; } \
		> build/lock/constraints.txt
	mv build/lock/constraints.txt constraints.txt

# ---------------------------------------------------------------------------------------- stages
# A plan variant (VARIANT=no-regrasp, no-tumble or no-usp: the paper's ablations) shares the graph;
# its plan, trajectories and execution go to $(B)/<variant>/ (the full planner: $(B)/full/).
VARIANT ?=
V := $(if $(VARIANT),$(VARIANT),full)
R := $(B)/$(V)
PLAN_FLAGS := $(if $(VARIANT),--$(VARIANT),)
# SEED 0 runs the nominal physics, N > 0 perturbs it; SEEDS=K also runs seeds 1..K (robustness.json).
SEED ?= 0
SEEDS ?= 0

# Each stage's outputs (<STAGE>_OUT, every file it writes) and prerequisites (<STAGE>_DEPS: its upstream
# outputs, the scene and the files it names, and every module its command imports, found from the import
# graph as gcc -M finds headers) come from `pivot deps`, which reads pivotcli/layout.py, the same rules
# `pivot run` follows. Regenerated when the scene or any code changes; only read for the stage targets.
DEPS := $(B)/.deps-$(V).mk
$(DEPS): $(SCENE_FILE) $(wildcard pivotcli/*.py stages/*.py stages/*/*.py) | $(INSTALLED)
	$(PIVOT) deps $(SCENE_FILE) --build $(B) --variant $(V) --out $@

ifneq ($(filter-out help install lint test bench golden clean benchmark reproduce demo lock browser,$(MAKECMDGOALS)),)
include $(DEPS)

$(ANALYZE_OUT) &: $(ANALYZE_DEPS) | $(INSTALLED)
	$(PIVOT) analyze --scene $(SCENE_FILE) --build $(B)

$(SAMPLE_OUT) &: $(SAMPLE_DEPS) | $(INSTALLED)
	$(PIVOT) sample $(SCENE_FILE) --build $(B)

$(GRAPH_OUT) &: $(GRAPH_DEPS) | $(INSTALLED)
	$(PIVOT) graph $(SCENE_FILE) --build $(B)

# pivot plan exits 1 when no plan exists; plan.json still records why, so Make keeps it.
$(PLAN_OUT) &: $(PLAN_DEPS) | $(INSTALLED)
	$(PIVOT) plan $(SCENE_FILE) --build $(B) $(PLAN_FLAGS) || [ $$? -eq 1 ]

$(MPC_OUT) &: $(MPC_DEPS) | $(INSTALLED)
	$(PIVOT) mpc $(SCENE_FILE) --build $(B) --variant $(V)

# pivot execute exits 1 when the object misses the goal in physics; execution.json records how.
$(EXECUTE_OUT) &: $(EXECUTE_DEPS) | $(INSTALLED)
	$(PIVOT) execute $(SCENE_FILE) --build $(B) --variant $(V) --seed $(SEED) --seeds $(SEEDS) || [ $$? -eq 1 ]

$(B)/analysis.png: $(ANALYZE_OUT) $(ANALYSIS_FIG_DEPS) | $(INSTALLED)
	$(PIVOT) show analysis $(B)/analysis --png $@

$(B)/poses.png: $(SAMPLE_OUT) $(POSES_FIG_DEPS) | $(INSTALLED)
	$(PIVOT) show poses $(B)/sample --scene $(SCENE_FILE) --png $@

$(R)/plan.png: $(PLAN_OUT) $(PLAN_FIG_DEPS) | $(INSTALLED)
	$(PIVOT) show plan $(B) --scene $(SCENE_FILE) --plan $(R)/plan.json --png $@

$(R)/trajectories.png: $(MPC_OUT) $(TRAJECTORIES_FIG_DEPS) | $(INSTALLED)
	$(PIVOT) show trajectories $(R)/trajectories.parquet --scene $(SCENE_FILE) --png $@

$(R)/execution.png: $(EXECUTE_OUT) $(EXECUTION_FIG_DEPS) | $(INSTALLED)
	$(PIVOT) show execution $(R) --png $@

# pivot view exits 1 when there is no motion to show (no plan); the page still shows the scene and why.
$(R)/view.html: $(PLAN_OUT) $(wildcard $(R)/trajectories.parquet $(R)/execution.json) $(VIEW_FIG_DEPS) | $(INSTALLED)
	$(PIVOT) view $(B) --scene $(SCENE_FILE) --variant $(V) --out $@ || [ $$? -eq 1 ]
endif

analysis: $(B)/analysis.png ## analyse the scene's object and draw it (Fig. 4)
sample: $(B)/poses.png ## sample object poses and their grasps, draw them (Fig. 10a)
plan: $(R)/plan.png ## build the graph, plan with backtracking and draw the plan (Fig. 10b)
mpc: $(R)/trajectories.png ## MPC force and joint trajectories of the plan, drawn (Fig. 12)
execute: $(R)/execution.png ## run the trajectories in PyBullet physics, storyboard + GIF (Fig. 15-18)
view: $(R)/view.html ## the plan beside its execution in 3D: one HTML page to turn and scrub, offline

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
	             execution.png execution.gif frames.npz robustness.json; do [ ! -f $$b/full/$$f ] || cp $$b/full/$$f $$b/$$v/; done; \
	    continue; fi; \
	  $(MAKE) --no-print-directory -s -k SCENE={} VARIANT=$$v SEEDS=10 mpc execute > /dev/null 2>&1 \
	    || echo "{} $${v:-full}: stopped"; \
	  done; echo "{}: done"'
	$(MAKE) --no-print-directory -s SCENE=exp1_reach_first VARIANT=no-regrasp plan > /dev/null 2>&1 || true
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

# The browser test drives Debian's chromium through chromedriver: installed here when missing and apt
# can (as root); where it cannot, the test is skipped and says why.
browser:
	@if ! command -v chromium > /dev/null || ! command -v chromedriver > /dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get > /dev/null; then \
	    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver; } \
	      > /dev/null 2>&1 || echo "make: chromium could not be installed; the browser test will be skipped"; \
	  else echo "make: no chromium and no apt-get as root; the browser test will be skipped"; fi; fi

# Tests run in TEST_WORKERS processes (pytest-xdist); the reference chains' tests share one (their
# xdist_group), so each chain is built once. TEST_WORKERS=0 runs them in this process.
TEST_WORKERS ?= 2
test: $(INSTALLED) lint browser ## install, lint and run the whole test suite
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup

bench: $(INSTALLED) ## print each stage's time beside its target and the paper's figure
	$(BIN)/python bench/run.py

# The reference scenes' chains, every stage, as readable digests tests/golden/<scene>.json (tests/golden.py),
# and the toy piano's analysis as artifacts; `make test` compares both.
golden: $(INSTALLED) ## regenerate the golden artifacts under tests/golden (review the diff before committing)
	rm -rf tests/golden/toy_piano
	$(PIVOT) analyze --scene data/scenes/default.json --out tests/golden/toy_piano
	rm -f tests/golden/toy_piano/object.ply tests/golden/toy_piano/*.timings.json
	$(BIN)/python -m tests.golden

clean: ## remove build outputs (keeps .venv)
	rm -rf build

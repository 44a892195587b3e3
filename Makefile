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

.PHONY: help install demo test lint bench analysis golden clean

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

# ------------------------------------------------------------------------------------------ jobs
demo: $(INSTALLED) $(B)/analysis.png ## run the pipeline on the default scene and draw its figures
	@echo "figures: $(B)/analysis.png"

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

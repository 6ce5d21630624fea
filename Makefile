SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.DEFAULT_GOAL := help
.PHONY: help setup test test-full wheel-smoke lint train train-full figures

help:  ## list the targets
	@grep -E '^[a-z-]+:.*##' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

$(PY):
	$(PYTHON) -m venv $(VENV)

# Re-install only when the dependency list changes; torch is pinned first so pip takes the
# CPU wheel available on the machine instead of a multi-GB CUDA build.
$(STAMP): pyproject.toml scripts/ensure_system_deps.sh | $(PY)
	bash scripts/ensure_system_deps.sh
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev,train,baselines,cluster]'
	touch $(STAMP)

setup: $(STAMP)  ## create .venv and install everything (idempotent)

test: setup  ## run the test suite (skips tests marked slow)
	$(PY) -m pytest

wheel-smoke: setup  ## build the wheel, install it into a throwaway venv, use it from outside the repo
	PY=$(PY) bash .ci/wheel_smoke.sh

test-full: setup  ## run every test, the slow ones included
	$(PY) -m pytest -m ''

lint: setup  ## ruff
	$(VENV)/bin/ruff check .

train: setup  ## train the embedded default: RPM-Net + line loss on procedural shapes (~10 min on 2 CPU cores)
	$(PY) -m train

train-full: setup  ## the paper's RPM-Net + line-loss configuration (python -m train experiment=rpm_ours recipe=paper)
	$(PY) -m train experiment=rpm_ours recipe=paper

figures: setup  ## draw docs/results/<protocol>.png (Err_R per seed of each cell) from docs/results/cells.csv
	$(PY) scripts/reproduce_report.py --cells docs/results/cells.csv --figures docs/results

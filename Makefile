# invrender: `make repro` runs the pipeline, `make test` the test suite; both install what they need first.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
LLVM_LIB := /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1
PORT ?= 5000

export DVC_NO_ANALYTICS := 1
export MLFLOW_SERVER_ENABLE_JOB_EXECUTION := false
# Mitsuba's llvm_ad_rgb variant only works with LLVM 19 (15/16 abort on the first render).
export DRJIT_LIBLLVM_PATH := $(LLVM_LIB)
export PATH := $(CURDIR)/$(VENV)/bin:$(PATH)

.PHONY: setup llvm chromium repro test test-fast lint deps ui clean-outputs

setup: $(STAMP) llvm chromium

# Reinstalls only when the lock file or the project metadata change.
$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -qq --disable-pip-version-check -r requirements.lock
	$(PY) -m pip install -qq --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $(STAMP)

# Without libLLVM 19 the generator falls back to the (2.4x slower) scalar_rgb variant.
llvm:
	@if [ ! -e $(LLVM_LIB) ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null; } \
	      || echo "warning: could not install libllvm19; Mitsuba will fall back to scalar_rgb (2.4x slower)"; \
	  else echo "note: libLLVM 19 missing and not root; Mitsuba will fall back to scalar_rgb"; fi; \
	fi

# Debian's chromium opens the MLflow UI headless in tests/test_ui.py (skipped, saying why, without it).
chromium:
	@if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } \
	      || echo "warning: could not install chromium; the MLflow UI browser test will be skipped"; \
	  else echo "note: chromium missing and not root; the MLflow UI browser test will be skipped"; fi; \
	fi

repro: setup
	$(VENV)/bin/dvc repro

test: setup
	$(PY) -m pytest -q -n 2 --dist loadgroup

test-fast: setup
	$(PY) -m pytest -q -n 2 --dist loadgroup -m "not slow"

lint: setup
	$(PY) -m ruff check pipeline stages tests
	$(PY) -m ruff format --check pipeline stages tests
	$(VENV)/bin/lint-imports
	$(PY) -m pipeline.tracking.stage_deps --check

# dvc.yaml's code and config deps (and params.yaml's per-ablation `conf` lists) from the import graph and
# the composed configs: run after adding an import, a stage, a config group option or an ablation entry.
deps: setup
	$(PY) -m pipeline.tracking.stage_deps --write

ui: setup
	@echo "MLflow UI on http://127.0.0.1:$(PORT)/#/experiments?workflowType=machine_learning (Ctrl-C to stop)"
	$(VENV)/bin/mlflow ui --backend-store-uri sqlite:///$(CURDIR)/mlflow.db \
	  --default-artifact-root file://$(CURDIR)/mlartifacts --host 127.0.0.1 --port $(PORT) --workers 1

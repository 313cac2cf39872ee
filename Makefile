# dbl-harness: every target that needs Python depends on the venv, so each works from a fresh clone.
# The Pythons the harness supports (pyproject.toml); make uses the first that runs here, unless
# PYTHON names one (a version manager's shim may exist for a version it cannot run).
PYTHON_VERSIONS := 3.11 3.12 3.13
ifeq ($(origin PYTHON),undefined)
PYTHON := $(or $(firstword $(foreach v,$(PYTHON_VERSIONS),$(shell python$(v) -c 'print("python$(v)")' 2>/dev/null))),python3.11)
endif
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# the packages installed, before their byte-compilation (lint and docs need no more)
PACKAGES := $(VENV)/.packages
DATA   ?=
CONFIG ?= datasets/fixture.toml
OUT    ?= results/fixture
TORCH_VERSION := 2.13.0
# torch's build: cpu (the default) from TORCH_INDEX, PyTorch's own CPU wheel index unless set (a
# URL or a folder in PEP 503 layout), or from a folder of wheels that pip's configuration names;
# TORCH=cuda: the GPU build with its CUDA libraries, from TORCH_INDEX or else pip's own index.
TORCH ?= cpu
TORCH_INDEX ?= $(if $(filter cuda,$(TORCH)),,https://download.pytorch.org/whl/cpu)
TORCH_STAMP := $(VENV)/.torch-$(TORCH)
# requirements.lock: every package but torch, exact and hashed (make lock writes it)
LOCK := requirements.lock
UV_VERSION := 0.13.8
# a folder holding torch's CPU wheel, whose metadata make lock reads (pip's find-links, where set)
TORCH_WHEELS ?= $(shell pip config get global.find-links 2>/dev/null)

.PHONY: help setup test lint docs bench real reproduce-table fixture clean lock

help:  ## Show this help
	@grep -E '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  %-18s %s\n", $$1, $$2}'

# The environment itself, repaired where an interrupted make left it half made.
$(BIN)/python:
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "ERROR: $(PYTHON) not found; set PYTHON=/path/to/python3.11 (3.11 to 3.13 work)"; exit 1; }
	$(PYTHON) -m venv $(VENV)

# torch first, before any large download: tools/install_torch.py reads the index's page for torch
# and stops with one ERROR: line where the build cannot be had (a stamp per build, so that
# TORCH=cuda after a CPU set-up replaces it).
$(TORCH_STAMP): | $(BIN)/python
	@$(BIN)/python -m pip --version >/dev/null 2>&1 || $(PYTHON) -m venv $(VENV)
	@rm -f $(PACKAGES) $(STAMP) $(VENV)/.torch-cpu $(VENV)/.torch-cuda
	$(BIN)/python tools/install_torch.py --version $(TORCH_VERSION) --build $(TORCH) --index "$(TORCH_INDEX)"
	@touch $@

# Every other package comes from the lock, exact and hashed, with no dependency resolution
# (--no-deps), installed by uv (its own version pinned here: 9 s where pip takes 71 s on this
# project's machines, the same files; pip where uv cannot be had); the package itself in place,
# built with the locked setuptools; pip check proves the set whole. The stamp is touched last, so
# a make that failed or was interrupted is taken up again by the next.
$(PACKAGES): pyproject.toml $(LOCK) $(TORCH_STAMP)
	( $(BIN)/python -m pip install -q --no-compile "uv==$(UV_VERSION)" \
	  && $(BIN)/uv pip install -q --python $(BIN)/python --require-hashes --no-deps -r $(LOCK) ) \
	  || $(BIN)/python -m pip install -q --no-compile --require-hashes --no-deps -r $(LOCK)
	$(BIN)/python -m pip install -q --no-compile --no-deps --no-build-isolation -e .
	$(BIN)/python -m pip check
	touch $(PACKAGES)

# Then everything is byte-compiled once, on both cores (about 45 s): where PYTHONDONTWRITEBYTECODE
# is set, as on this project's machines, nothing else ever writes a .pyc, and every process (each
# CLI run, Ray worker, test subprocess) would compile torch and pandas again: 9.5 s to import the
# pipeline instead of 3.6 s (measured; a file that does not compile, such as a package's Python-2
# example, is skipped). The packages' own test suites (their tests/ folders: a fifth of the files)
# are never imported, so never compiled. .ci/run compiles beside the lint and the site.
$(STAMP): $(PACKAGES)
	$(BIN)/python -m compileall -q -j 0 -x '/tests/' $(VENV)/lib harness > /dev/null 2>&1 || true
	touch $(STAMP)

setup: $(STAMP)  ## Create .venv and install the locked packages, torch (TORCH=cuda: GPU build), the package

# The newest versions pyproject.toml's ranges allow, for Python 3.11 on x86-64 Linux, with the
# hashes of every file of each; torch's own dependencies from its CPU wheel's metadata (found in
# TORCH_WHEELS), torch itself left to setup. Then run make test: the suite must pass on the new set.
lock:  ## Upgrade requirements.lock deliberately (then make test, and commit it with the results)
	@test -n "$(TORCH_WHEELS)" || { echo "ERROR: set TORCH_WHEELS=DIR, a folder holding the torch $(TORCH_VERSION)+cpu wheel"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q "uv==$(UV_VERSION)"
	printf 'torch==$(TORCH_VERSION)+cpu\n' > $(VENV)/lock-constraints.txt
	$(BIN)/uv pip compile pyproject.toml requirements-build.in --extra dev --upgrade \
	  --generate-hashes --python-version 3.11 --python-platform x86_64-manylinux_2_28 \
	  --find-links $(TORCH_WHEELS) -c $(VENV)/lock-constraints.txt --no-emit-package torch \
	  --custom-compile-command "make lock" -o $(LOCK)
	rm -f $(STAMP) $(PACKAGES)
	@echo "wrote $(LOCK); now: make test"

# Two workers, each test file on one (its module fixtures computed once); the fixture runs every
# file shares are computed once per session across both (tests/conftest.shared_stages). Each
# worker keeps torch's two threads (the model's bits depend on the thread count), so idle OpenMP
# threads sleep rather than spin (OMP_WAIT_POLICY: scheduling only, no result changes).
TEST_WORKERS ?= 2
test: $(STAMP)  ## Run the whole test suite (CI runs exactly this)
	OMP_WAIT_POLICY=PASSIVE $(BIN)/python -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

lint: $(PACKAGES)  ## ruff (rules, line length 100, formatting) and mypy (strict on the numeric kernels)
	$(BIN)/ruff check harness tests bench examples tools
	$(BIN)/ruff format --check harness tests bench examples tools
	$(BIN)/mypy

# The manual as a site (mkdocs.yml; the pages are docs/*.md), built with --strict: a broken link,
# a missing page or a plugin API page that does not resolve fails. The configuration page must be
# what the code says (python -m harness.config.reference --write regenerates it).
docs: $(PACKAGES)  ## Build the documentation site into site/ (--strict), after checking docs/config.md
	$(BIN)/python -m harness.config.reference --check
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

bench: $(STAMP)  ## Run the benchmarks; results go to results/bench/
	$(BIN)/python -m bench

# The detector's candidates on real revisits (../shared/realdata/obchange-dev, read where it lies,
# never copied into the repository): Table D's detector row and the candidates' recall of each.
real: $(STAMP)  ## harness detect's default and alternatives on the real pairs in ../shared/realdata
	$(BIN)/python -m bench.detect_choice --sets obchange-dev

# With no arguments: the bundled fixture. DATA=/path/to/nclt uses datasets/nclt.toml with that root.
reproduce-table: $(STAMP)  ## Run the whole pipeline and print Table I (CONFIG=..., DATA=..., OUT=...)
ifeq ($(strip $(DATA)),)
	$(BIN)/harness reproduce --config $(CONFIG) --out $(OUT)
else
	$(BIN)/harness reproduce --config datasets/nclt.toml --data-root $(DATA) --out results/nclt
endif

fixture: $(STAMP)  ## (Re)generate the fixture world under datasets/fixture
	$(BIN)/harness fixture --out datasets/fixture

clean:  ## Remove the venv and run outputs (not the committed regression table)
	rm -rf $(VENV) results/fixture results/nclt

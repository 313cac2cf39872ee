# dbl-harness: every target that needs Python depends on the venv, so each works from a fresh clone.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DATA   ?=
CONFIG ?= datasets/fixture.toml
OUT    ?= results/fixture
TORCH_VERSION := 2.13.0

.PHONY: help setup test lint bench reproduce-table fixture clean

help:  ## Show this help
	@grep -E '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  %-18s %s\n", $$1, $$2}'

# --no-compile: a module is byte-compiled when first imported, rather than every file of torch at
# install (measured: torch's install 35 s -> 18 s)
$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "ERROR: $(PYTHON) not found; set PYTHON=/path/to/python3.11"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q --no-compile "torch==$(TORCH_VERSION)"
	$(BIN)/python -m pip install -q --no-compile -e ".[dev]"
	touch $(STAMP)

setup: $(STAMP)  ## Create .venv and install torch, the package and its dev tools

test: $(STAMP)  ## Run the whole test suite (CI runs exactly this)
	$(BIN)/python -m pytest -q -p no:cacheprovider

lint: $(STAMP)  ## ruff (rules, line length 100, formatting) and mypy (strict on the numeric kernels)
	$(BIN)/ruff check harness tests bench examples
	$(BIN)/ruff format --check harness tests bench examples
	$(BIN)/mypy

bench: $(STAMP)  ## Run the benchmarks; results go to results/bench/
	$(BIN)/python -m bench

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

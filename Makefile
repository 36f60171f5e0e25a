# `make demo` and `make test` bootstrap .venv on a fresh machine, then run.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
export OPENBLAS_NUM_THREADS := 1

.PHONY: demo test bench venv clean

venv: $(STAMP)

# torch is pinned to its CPU build (README.md, Install);
# installing it first keeps pip from resolving a multi-GB CUDA build.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

# DEMO=--through-drivers: the real drivers instead of virtual time; DEMO=--fresh: start over.
demo: $(STAMP)
	$(BIN)/python tools/demo.py demo-out $(DEMO)

test: $(STAMP)
	$(BIN)/ruff check labrig tests tools
	$(BIN)/mypy
	$(BIN)/lint-imports --no-cache
	$(BIN)/python -m pytest -q -n auto -m "not serial" --durations=15
	$(BIN)/python -m pytest -q -m serial --durations=10

bench: $(STAMP)
	$(BIN)/python tools/bench/run_all.py

clean:
	rm -rf $(VENV) demo-out .pytest_cache

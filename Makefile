# Two entry points a new user needs: `make demo` and `make test`. Each creates .venv and installs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test lint bench clean

$(BIN)/relloc: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,train]'
	touch $(BIN)/relloc

setup: $(BIN)/relloc

demo: setup
	$(BIN)/relloc demo --seed 0 --out out/demo --json out/demo/demo.json

test: setup
	$(BIN)/ruff check src tests benchmarks examples
	$(BIN)/python -m pytest -q

# The benchmark has an environment of its own: relloc plus the pfilter reference (not a dependency).
BENCH_VENV := .venv-bench
BENCH_ARGS ?= --json out/bench/filter_vs_pfilter.json

$(BENCH_VENV)/.installed: pyproject.toml benchmarks/requirements-pfilter.txt
	$(PYTHON) -m venv $(BENCH_VENV)
	$(BENCH_VENV)/bin/python -m pip install -q --upgrade pip
	$(BENCH_VENV)/bin/python -m pip install -q -e . -r benchmarks/requirements-pfilter.txt
	touch $@

bench: $(BENCH_VENV)/.installed
	$(BENCH_VENV)/bin/python benchmarks/filter_vs_pfilter.py $(BENCH_ARGS)

clean:
	rm -rf $(VENV) out build *.egg-info

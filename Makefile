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

bench: setup
	$(BIN)/python benchmarks/filter_vs_pfilter.py

clean:
	rm -rf $(VENV) out build *.egg-info

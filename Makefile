# Two entry points a new user needs: `make demo` and `make test`. Each creates .venv and installs.
# `make demo` installs relloc alone (no PyTorch); `make test` adds the dev tools and the training
# extra (PyTorch), because the test suite trains small models; it checks lint, format and types
# (mypy on src/, configured in pyproject.toml) before the tests, which run on two workers
# (pytest-xdist; `-p no:xdist` or `-n 0` runs them in one process).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup setup-test demo test docs results results-mrclam lint bench clean

# A .venv made by another Python cannot be reused (pip refuses relloc with "requires a different
# Python", and `python -m venv` keeps the old interpreter): say so and rebuild it.
define fresh_venv
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "relloc needs Python 3.11 or newer; this is " + sys.version.split()[0] + " (set PYTHON=python3.11)")'
	@want=$$($(PYTHON) -c 'import sys; print(sys.version.split()[0])'); \
	have=$$($(BIN)/python -c 'import sys; print(sys.version.split()[0])' 2>/dev/null || true); \
	if [ -d $(VENV) ] && [ "$$have" != "$$want" ]; then \
		echo "$(VENV) was made with Python $${have:-unknown}, not $$want: rebuilding it"; rm -rf $(VENV); \
	fi
	@[ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
endef

$(VENV)/.installed-core: pyproject.toml
	$(fresh_venv)
	$(BIN)/python -m pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml
	$(fresh_venv)
	$(BIN)/python -m pip install -q -e '.[dev,train]'
	touch $@ $(VENV)/.installed-core

setup: $(VENV)/.installed-core

setup-test: $(VENV)/.installed-test

demo: setup
	$(BIN)/relloc demo --seed 0 --out out/demo --json out/demo/demo.json

test: setup-test
	$(BIN)/ruff check src tests benchmarks examples scripts
	$(BIN)/ruff format --check src tests benchmarks examples scripts
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n 2 --dist worksteal

# The documentation site: its own environment (relloc and the `docs` extra); the command, config
# and Python API reference pages are generated at build time by the hook docs/gen_reference.py.
DOCS_VENV := .venv-docs

$(DOCS_VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(DOCS_VENV)
	$(DOCS_VENV)/bin/python -m pip install -q --upgrade pip
	$(DOCS_VENV)/bin/python -m pip install -q -e '.[docs]'
	touch $@

docs: $(DOCS_VENV)/.installed
	NO_MKDOCS_2_WARNING=1 $(DOCS_VENV)/bin/mkdocs build --strict --quiet

# Reruns the evaluation commands and the benchmarks that take seconds and writes docs/results/index.md
# from their JSON, and the first-run tutorial's output and plot (docs/generated/): about 4 min on
# 2 cores. `results-mrclam` is the long sweep, MRCLAM Dataset 6 with every robot as the
# reference, seeds 0-2 (15 runs, two at a time, about 20 min; skipped without ../shared/data):
# docs/results/mrclam_references_generated.md.
results: setup
	$(BIN)/python scripts/results_pages.py --out docs/results/index.md --generated docs/generated

results-mrclam: setup
	$(BIN)/python scripts/mrclam_references.py --skip-missing --page docs/results/mrclam_references_generated.md

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
	rm -rf $(VENV) $(BENCH_VENV) $(DOCS_VENV) out build *.egg-info

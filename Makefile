# Two commands on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

$(BIN)/rlbackdoors: pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e '.[test,docs]'  # pip compiles the bytecode: with PYTHONDONTWRITEBYTECODE set, nothing else would
	touch $@

.PHONY: install demo test test-slow bench docs
install: $(BIN)/rlbackdoors

demo: install
	$(BIN)/rlbackdoors demo

test: install
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/mypy
	$(BIN)/python -m compileall -q src  # bytecode for the package: every test's child process reads it (PYTHONDONTWRITEBYTECODE stops them writing it)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir .site  # the docs site: a broken link, anchor or missing page fails (not --quiet: with it, an aborted strict build exits 0)
	$(BIN)/python -m pytest -q -n auto --dist loadfile  # one worker per core, a test file per worker (pytest-xdist)

docs: install
	$(BIN)/mkdocs serve  # the docs site at http://127.0.0.1:8000 (mkdocs build --strict writes it to .site/)

test-slow: install
	$(BIN)/python -m pytest -q -m slow

bench: install
	$(BIN)/rlbackdoors bench train --json benchmarks/results/train.json
	$(BIN)/rlbackdoors bench env --json benchmarks/results/env.json
	$(BIN)/rlbackdoors bench converge --quiet --json benchmarks/results/converge.json
	$(BIN)/rlbackdoors bench env --env safety-car-goal --json benchmarks/results/safety.json

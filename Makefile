# Set-up and the two main jobs. Each target creates .venv on first use and installs torch 2.13.0
# (a CPU build) before the project, so the project's torch>=2.3 requirement is already met.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
RECIPE ?= recipes/pendulum/tla-c.toml
OUT    ?= runs/$(basename $(notdir $(RECIPE)))-$(shell date +%Y%m%d-%H%M%S)

.PHONY: run test lint bench

run: $(VENV)/.installed
	$(BIN)/layered train $(RECIPE) --out $(OUT)

test: $(VENV)/.installed
	$(BIN)/python -m pytest -q

lint: $(VENV)/.installed
	$(BIN)/ruff check layered envs tests benchmarks
	$(BIN)/mypy layered envs

bench: $(VENV)/.installed
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	$(BIN)/python benchmarks/td3_vs_sb3.py

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $@

# Set-up and the two main jobs. Each target creates .venv on first use and installs torch 2.13.0
# (a CPU build) before the project, so the project's torch>=2.4 requirement is already met.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
RECIPE ?= recipes/pendulum/tla-c.toml
OUT    ?= runs/$(basename $(notdir $(RECIPE)))-$(shell date +%Y%m%d-%H%M%S)

.PHONY: run test lint bench wheel-check learning-check gpu-check

run: $(VENV)/.installed
	$(BIN)/layered train $(RECIPE) --out $(OUT)

# The default suite, its tests shared out over one process per core (pytest-xdist).
test: $(VENV)/.installed
	$(BIN)/python -m pytest -q -n auto

# Pendulum TLA-C at the recipe's budget, 2 seeds, against the paper's numbers (TD3's beside it: pytest -m slow).
learning-check: $(VENV)/.installed
	$(BIN)/python -m pytest -q -m learning tests/test_learning.py

# On a machine with a CUDA GPU: the tests that need one (they skip elsewhere), then the speed targets.
gpu-check: $(VENV)/.installed
	$(BIN)/python -m pytest -q -k "cuda or cudagraphs or gpu"
	$(BIN)/python benchmarks/gpu.py --parts targets --modes cudagraphs --group-modes cudagraphs --group-workers auto --splits 1,2

# The wheel, installed with its extras into a clean environment, trains a shipped recipe (named, not a
# path) and exports it, outside the checkout.
wheel-check: $(VENV)/.installed
	rm -rf dist .wheel-venv
	$(BIN)/python -m pip install --quiet build
	$(BIN)/python -m build --wheel --outdir dist .
	$(PYTHON) -m venv .wheel-venv
	.wheel-venv/bin/python -m pip install --quiet torch==2.13.0
	.wheel-venv/bin/python -m pip install --quiet "$$(ls dist/*.whl)[onnx,tensorboard]"
	cd "$$(mktemp -d)" && $(CURDIR)/.wheel-venv/bin/layered train pendulum/tla-c --steps 300 --out run \
		train.warmup=100 eval.every=150 eval.episodes=1 eval.fresh_episodes=1 && \
		$(CURDIR)/.wheel-venv/bin/layered export run --format onnx

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

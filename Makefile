# Set-up and the two main jobs. Each target creates .venv on first use and installs torch 2.13.0
# (a CPU build) before the project, so the project's torch>=2.4 requirement is already met.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
RECIPE ?= recipes/pendulum/tla-c.toml
OUT    ?= runs/$(basename $(notdir $(RECIPE)))-$(shell date +%Y%m%d-%H%M%S)

WHEEL_PYTHON ?= $(shell $(PYTHON) -c 'import sys; print("%d.%d" % sys.version_info[:2])')
WHEEL_EXTRAS ?=

.PHONY: run test lint bench wheelhouse wheel-check learning-check gpu-check

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

# For a machine without a package index that has its own torch (a cluster's GPU node): the project's wheel
# and every dependency but torch, as wheels for Python $(WHEEL_PYTHON) on this platform, with the extras named in
# WHEEL_EXTRAS (e.g. onnx,tensorboard). There: pip install --no-index --find-links wheelhouse layered-control
wheelhouse: $(VENV)/.installed
	requirements="$$($(BIN)/python -c "$$REQUIREMENTS_BUT_TORCH" "$(WHEEL_EXTRAS)")" && rm -rf wheelhouse && \
		mkdir wheelhouse && printf '%s\n' "$$requirements" > wheelhouse/requirements.txt
	$(BIN)/python -m pip install --quiet build
	$(BIN)/python -m build --wheel --outdir wheelhouse .
	$(BIN)/python -m pip download --quiet --dest wheelhouse --only-binary=:all: --python-version $(WHEEL_PYTHON) \
		--requirement wheelhouse/requirements.txt

# The project's requirements (with the extras named in its argument) less torch and the project itself, a line each.
define REQUIREMENTS_BUT_TORCH
import re, sys, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
extras, known = [name for name in sys.argv[1].split(",") if name], project["optional-dependencies"]
if unknown := [name for name in extras if name not in known]:
    sys.exit(f"WHEEL_EXTRAS: no extra {unknown[0]!r}; the extras: {', '.join(known)}")
wanted = project["dependencies"] + [r for name in extras for r in known[name]]
print("\n".join(r for r in wanted if re.match(r"[\w.-]+", r)[0] not in ("torch", project["name"])))
endef
export REQUIREMENTS_BUT_TORCH

# The wheel and its extras, installed from the wheelhouse alone into a clean environment, train a shipped
# recipe (named, not a path) and export it, outside the checkout.
wheel-check: WHEEL_EXTRAS = onnx,tensorboard
wheel-check: wheelhouse
	rm -rf .wheel-venv
	$(PYTHON) -m venv .wheel-venv
	.wheel-venv/bin/python -m pip install --quiet torch==2.13.0
	.wheel-venv/bin/python -m pip install --quiet --no-index --find-links wheelhouse "layered-control[onnx,tensorboard]"
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

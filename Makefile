# reach-stack: `make demo` and `make test` do all set-up on a fresh machine.
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed
BSTAMP := $(VENV)/.installed-bench

.PHONY: install test lint typecheck pytest bench demo readme-sample clean

$(PY):
	python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip

# What each target installs (pyproject.toml's extras): `make demo` the base install (driver,
# reach-driver, recordings, pid and ddpg) and `sim` (MuJoCo, reach-sim); `make test` everything:
# `dev`, `scale` and `all` (sim, mpc, train, scale, export).
#
# torch comes only with `train` (in `all`), and on a stock index pip would pick a CUDA build
# (several GB). So it is installed first, pinned and from TORCH_INDEX, and every later install
# is held to that pin (--constraint): what follows finds torch satisfied and can never swap it.
# On a machine whose default index serves CUDA wheels (stock PyPI on Linux):
#   make test TORCH_INDEX=https://download.pytorch.org/whl/cpu
# (TORCH_VERSION=... for another pinned version: a new pin file, so torch is installed again).
TORCH_VERSION ?= 2.13.0
TORCH_INDEX   ?=
TORCH_FLAGS   := $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
TORCH_PIN     := $(VENV)/torch-$(TORCH_VERSION).pin
DSTAMP        := $(VENV)/.installed-demo

$(TORCH_PIN): | $(PY)
	$(PIP) install -q $(TORCH_FLAGS) torch==$(TORCH_VERSION)
	echo "torch==$(TORCH_VERSION)" > $(TORCH_PIN)

$(STAMP): pyproject.toml $(TORCH_PIN)
	$(PIP) install -q --constraint $(TORCH_PIN) -e '.[dev,scale,all]'
	touch $(STAMP)

$(BSTAMP): $(STAMP)
	$(PIP) install -q --constraint $(TORCH_PIN) -e '.[dev,scale,all,bench]'
	touch $(BSTAMP)

# The demo needs no torch, CasADi or Ray.
$(DSTAMP): pyproject.toml | $(PY)
	$(PIP) install -q -e '.[sim]'
	touch $(DSTAMP)

install: $(STAMP)

lint: install
	$(VENV)/bin/ruff check protocol reach_driver reach_sim_bridge policy tests tools
	$(VENV)/bin/ruff format --check protocol reach_driver reach_sim_bridge policy tests tools

# The packages (pyproject's [tool.mypy] list), then the tests and tools: not packages (no
# __init__.py), each file a top-level module as pytest and the tools' own sys.path see them.
typecheck: install
	$(VENV)/bin/mypy
	$(VENV)/bin/mypy tests tools

# pytest exits 5 when it collects nothing: say so plainly and fail (an empty run proves nothing).
# Every test runs once, spread over the cores (pytest-xdist): the real-time ones wait on events
# and count in the arm's time, so a loaded host makes them slower, not red (tests/conftest.py).
# The 15 slowest are listed at the end: the aim is under 10 minutes on 2 cores (not yet met).
pytest: install
	@$(VENV)/bin/pytest -q -n auto --durations=15; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing" >&2; fi; exit $$rc

test: lint typecheck pytest

# Every benchmark runs and prints its figures; the target fails at the end naming those that
# missed their aim (a miss no longer hides the benchmarks after it).
bench: $(BSTAMP)
	@missed=""; for b in tools/bench_*.py; do echo "== $$b"; $(PY) $$b || missed="$$missed $$b"; done; \
	if [ -n "$$missed" ]; then echo "benchmarks that missed their aim:$$missed" >&2; exit 1; fi; \
	echo "all benchmarks met their aims"

# The shipped learned controller (ddpg: learned by RL from scratch)
# through `reach-driver` on the virtual arm, real time (~25 s); writes demo.rrd.
# e.g. make demo DEMO_ARGS="--speed 4 --scenario 3"
demo: $(DSTAMP)
	$(PY) tools/demo.py $(DEMO_ARGS)

# README.md's sample output, from a real run of the command it shows against the virtual arm
# (real time, a few seconds); tests/test_readme_sample.py checks it still holds.
readme-sample: $(DSTAMP)
	$(PY) tools/readme_sample.py --write

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache

# reach-stack: `make demo` and `make test` do all set-up on a fresh machine.
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed
BSTAMP := $(VENV)/.installed-bench

.PHONY: install test lint typecheck pytest bench demo clean

$(PY):
	python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip

# torch first, pinned to the CPU wheel that lies on these machines' disk, so nothing pulls CUDA.
$(STAMP): pyproject.toml | $(PY)
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[dev]'
	touch $(STAMP)

$(BSTAMP): $(STAMP)
	$(PIP) install -q -e '.[dev,bench]'
	touch $(BSTAMP)

install: $(STAMP)

lint: install
	$(VENV)/bin/ruff check protocol reach_driver reach_sim_bridge policy tests tools

typecheck: install
	$(VENV)/bin/mypy

# pytest exits 5 when it collects nothing: say so plainly and fail (an empty run proves nothing).
pytest: install
	@$(VENV)/bin/pytest -q; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing" >&2; fi; exit $$rc

test: lint typecheck pytest

bench: $(BSTAMP)
	@for b in tools/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

# The shipped DDPG through `reach-driver` on the virtual arm, real time (~25 s); writes demo.rrd.
# e.g. make demo DEMO_ARGS="--speed 4 --scenario 3"
demo: install
	$(PY) tools/demo.py $(DEMO_ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache

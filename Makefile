# One command per job: `make demo` runs the main job, `make test` the test suite, `make compose`
# the containers. Nothing is exported: every command runs as it would from a plain shell (the
# product picks its rendering backend itself). `make demo` needs no root, no compiler and no YARP:
# it installs the package with `[all]` from wheels; the development tools (`[dev]`) and YARP
# (built from source, ~7 minutes) come only with the targets that use them.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup dev yarp demo test compose lint format bench bench-smoke wheel-check drills clean

# movement-primitives is published as source only, and its build compiles an optional C extension
# whenever Cython is at hand, which the project does not use (the DMPs integrate with "rk4", in
# Python): built without build isolation, where no Cython is installed, it needs no compiler.
MOVEMENT := $(shell grep -o '"movement-primitives[^"]*"' pyproject.toml | tr -d '"')

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel
	$(PY) -m pip install -q --no-build-isolation '$(MOVEMENT)'
	$(PY) -m pip install -q -e '.[all]'
	touch $@

# pytest, ruff, mypy and the tests' reference libraries
$(VENV)/.dev: $(VENV)/.installed
	$(PY) -m pip install -q -e '.[dev]'
	touch $@

# YARP 3.5 for `archery yarp` and its tests: built once per machine from PyPI's source
# distribution when this environment cannot `import yarp` (tools/yarp_wheel.py; ~7 minutes)
$(VENV)/.yarp: $(VENV)/.installed tools/yarp_wheel.py
	$(PY) tools/yarp_wheel.py
	touch $@

setup: $(VENV)/.installed

dev: $(VENV)/.dev

yarp: $(VENV)/.yarp

demo: setup
	$(VENV)/bin/archery demo

test: dev yarp
	$(PY) -m pytest

# The containers for real: images, docker-compose's demo, secure and fleet profiles, faults.
compose: dev
	$(PY) -m tests.containers

lint: dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

format: dev
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

bench: dev
	$(PY) -m benchmarks.run

# Every benchmark at its smallest budget: they still run against today's code.
bench-smoke: dev
	$(PY) -m benchmarks.run --smoke

# The wheel as a user installs it: built once, installed with [all] into a fresh venv outside the
# checkout (not editable), `archery demo` run from another folder in a bare environment; then on
# each of OTHER_PYTHONS the demo and a fast subset of the tests (the full suite runs on 3.11).
OTHER_PYTHONS ?= 3.12,3.13
wheel-check: dev
	$(PY) -m tests.wheel_check --pythons $(OTHER_PYTHONS)

drills: dev
	$(VENV)/bin/archery drill

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache .mypy_cache

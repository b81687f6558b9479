# `make test`, `make check` and `make demo` each install what they need into .venv first.
PYTHON ?= python3
VENV := .venv
# Byte-code is written, whatever the shell says: without it every test worker rewrote the asserts of
# 270 plugin modules (16 s each on a 2-core AMD EPYC) and every process started compiled the sources.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: test unit check demo bench clean

# One `pip install` an extra (it brings the core with it), without compiling every installed module
# to byte-code: Python writes it for the modules a process imports, on first import. Two installs
# with compiling took 91 s on a 2-core AMD EPYC, one without 40 s and the first imports 8 s more.
$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip

$(VENV)/.core: pyproject.toml | $(VENV)/bin/python
	$(VENV)/bin/pip install --quiet --no-compile -e .
	touch $@

$(VENV)/.dev: pyproject.toml | $(VENV)/bin/python
	$(VENV)/bin/pip install --quiet --no-compile -e '.[dev]'
	touch $(VENV)/.core $@

$(VENV)/.bench: pyproject.toml | $(VENV)/bin/python
	$(VENV)/bin/pip install --quiet --no-compile -e '.[bench]'
	touch $(VENV)/.core $@

test: $(VENV)/.dev
	@command -v chromium >/dev/null || [ "$$(id -u)" != 0 ] || (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) || echo "could not install chromium: the viewer screenshot test will be skipped"
	@command -v docker-compose >/dev/null || [ "$$(id -u)" != 0 ] || (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq docker-compose >/dev/null) || echo "could not install docker-compose: the compose file validation test will be skipped"
	$(VENV)/bin/pytest -q -n 2 --dist worksteal --durations=15

unit: $(VENV)/.dev
	$(VENV)/bin/pytest -q -m "not integration"

check: $(VENV)/.dev
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy gmm_core protocol

demo: $(VENV)/.core
	$(VENV)/bin/gmmap demo

bench: $(VENV)/.bench
	$(VENV)/bin/python bench/fit.py
	$(VENV)/bin/python bench/raytrace.py
	$(VENV)/bin/python bench/auroc_intel.py

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache

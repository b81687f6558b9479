# `make test`, `make check` and `make demo` each install what they need into .venv first.
PYTHON ?= python3
VENV := .venv
# Byte-code is written, whatever the shell says: without it every test worker rewrote the asserts of
# 270 plugin modules (16 s each on a 2-core AMD EPYC) and every process started compiled the sources.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: test unit check demo bench clean

$(VENV)/.core: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet -e .
	touch $@

$(VENV)/.dev: $(VENV)/.core
	$(VENV)/bin/pip install --quiet -e '.[dev]'
	touch $@

$(VENV)/.bench: $(VENV)/.core
	$(VENV)/bin/pip install --quiet -e '.[bench]'
	touch $@

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

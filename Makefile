# Two commands for a fresh machine: `make run` (the main job) and `make test` (lint, then the test suite).
# Both create .venv with python3 (3.11 or 3.12) and install the project into it; the install is redone only
# when pyproject.toml changes (the stamp file below), so later runs start at once.

PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.impulse-installed

.PHONY: run test venv

run: $(STAMP)
	$(VENV)/bin/impulse train --config configs/quick-cpu.toml

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pytest

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

.PHONY: run test
run: $(STAMP)
	$(PY) -m benchmarks.engine --quick

test: $(STAMP)
	$(VENV)/bin/ruff check .
	JAX_COMPILATION_CACHE_DIR=.cache/jax $(VENV)/bin/pytest

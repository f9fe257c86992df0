# Two entry points for a fresh machine: `make demo` and `make test`. Both create/update .venv only when
# pyproject.toml changed (the stamp files), so a second run starts at once.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PIP_FLAGS := --disable-pip-version-check --quiet

.PHONY: demo test lint mutations clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install $(PIP_FLAGS) --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install $(PIP_FLAGS) -e .
	touch $@

$(VENV)/.installed-dev: pyproject.toml $(VENV)/.installed
	$(BIN)/python -m pip install $(PIP_FLAGS) -e '.[dev,ray,peers]'
	touch $@

demo: $(VENV)/.installed
	$(BIN)/volren demo

lint: $(VENV)/.installed-dev
	$(BIN)/ruff check src tests scripts

test: lint
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q

# Every paper part's deliberate breakage must fail its tests (tests/mutations.toml); slow, not part of `make test`.
mutations: $(VENV)/.installed-dev
	$(BIN)/python scripts/mutations.py

clean:
	rm -rf $(VENV) out .pytest_cache

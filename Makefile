# Two entry points for a fresh machine: `make demo` and `make test`. Both create/update .venv only when
# pyproject.toml changed (the stamp files), so a second run starts at once.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PIP_FLAGS := --disable-pip-version-check --quiet

.PHONY: demo test lint cuda-check wheel-check docs mutations clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install $(PIP_FLAGS) --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install $(PIP_FLAGS) -e .
	touch $@

$(VENV)/.installed-dev: pyproject.toml $(VENV)/.installed
	$(BIN)/python -m pip install $(PIP_FLAGS) -e '.[dev,ray,peers,docs]'
	touch $@

demo: $(VENV)/.installed
	$(BIN)/volren demo

lint: $(VENV)/.installed-dev
	$(BIN)/ruff check src tests scripts

# Every Warp kernel module compiled for CUDA sm_80 and sm_90 through NVRTC, no GPU needed (scripts/cuda_check.py):
# about 140 s on 2 cores the first time, 3 s when Warp's kernel cache already holds the unchanged modules.
cuda-check: $(VENV)/.installed-dev
	$(BIN)/python scripts/cuda_check.py

# The sdist and wheel built, the wheel installed into a fresh venv with no source tree beside it, and run there.
wheel-check: $(VENV)/.installed-dev
	bash scripts/wheel_check.sh $(BIN)/python

# The documentation site into site/ (mkdocs.yml): offline, strict, every relative link and anchor checked.
docs: $(VENV)/.installed-dev
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

test: lint cuda-check
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q

# Every paper part's deliberate breakage must fail its tests (tests/mutations.toml); slow, not part of `make test`.
mutations: $(VENV)/.installed-dev
	$(BIN)/python scripts/mutations.py

clean:
	rm -rf $(VENV) out site .pytest_cache

# The two commands: `make run` (the main job) and `make test` (the test suite, the documentation's
# code blocks included, and the strict documentation build). Each sets everything up on first use:
# a virtual environment in .venv/, the CPU build of torch FIRST (installed after the package, pip
# would pull a multi-gigabyte CUDA build), then the package in editable mode with its extras.
# `make lint` runs the checks CI runs besides the tests (ruff, mypy).

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-torchsde_lti
TORCH ?= torch==2.13.0
EXTRAS ?= test,data,launchers,docs,dev
export NO_MKDOCS_2_WARNING := 1
export DISABLE_MKDOCS_2_WARNING := true

.PHONY: run test lint docs serve clean

$(STAMP): pyproject.toml setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet "$(TORCH)"
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	touch $(STAMP)

run: $(STAMP)
	$(PY) -m torchsde_lti.train

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow"
	$(PY) -m mkdocs build --strict --quiet --site-dir $(VENV)/site

lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy

docs: test

serve: $(STAMP)
	$(PY) -m mkdocs serve

clean:
	rm -rf $(VENV) site

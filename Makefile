# lidarjax: the two commands (`make demo`, `make test`) set everything up themselves.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: notebooks demo test test-slow test-all bench lint install native clean docs

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Re-install only when pyproject.toml changed since the last install.
$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP) native

# Native ray kernels (C++ through the XLA FFI, headers of the installed jaxlib). The build
# script rebuilds only when a C++ source, the jaxlib version or the flags changed; without
# a compiler it says so and the pure-JAX path is used.
native: $(STAMP)
	$(PY) -m lidarjax.raytrace._build --optional

demo: install
	$(PY) experiments/demo.py

# The suite without the tests marked slow (long real-data runs); CI runs both targets.
# Test files are spread over TEST_WORKERS processes (pytest-xdist; default: the cores, at
# most 4, each worker holds ~2 GB of compiled code); the slowest 20 tests are reported.
# Compiled programs are cached between runs in ~/.cache/lidarjax (tests/conftest.py;
# LIDARJAX_JAX_CACHE=off disables it).
TEST_WORKERS ?= $(shell $(PYTHON) -c "import os; print(max(1, min(4, len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1))))")
# Fast tests go by file (module fixtures built once); the slow ones, a few minutes each and
# many in one file, are handed out one by one to whichever worker is free. The slow tests
# spend much of their time in XLA's compiler, one thread per program (on 2 cores two
# workers kept 1.3 cores busy): they run on one worker more than the cores (at most 4).
PYTEST := $(PY) -m pytest -q --durations=20
SLOW_WORKERS ?= $(shell $(PYTHON) -c "print(min(4, $(TEST_WORKERS) + 1))")

test: install
	$(VENV)/bin/ruff check .
	$(PYTEST) -n $(TEST_WORKERS) --dist loadfile -m "not slow"

test-slow: install
	$(PYTEST) -n $(SLOW_WORKERS) --dist worksteal -m slow

test-all: test test-slow

bench: install
	@set -e; for b in benchmarks/[a-z]*.py; do echo "== $$b"; $(PY) $$b; done

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check lidarjax tests experiments benchmarks

# The documentation site (mkdocs.yml, docs/: guide, results, API reference from the
# docstrings) -> site/. --strict turns every warning (a broken link or anchor, an unresolved
# cross-reference, a docstring griffe cannot read) into a failure. The docs extra is
# installed once per pyproject.toml change, like the dev extra.
DOCS_STAMP := $(VENV)/.docs-stamp

$(DOCS_STAMP): pyproject.toml | $(STAMP)
	$(PY) -m pip install --quiet -e '.[docs]'
	touch $(DOCS_STAMP)

# The notebooks' .py files (Jupytext percent scripts) are the source; this writes the
# paired .ipynb (no outputs; edit the .py, not the .ipynb) (tests/test_notebooks.py checks they are in sync and runs
# them in a Jupyter kernel).
notebooks: $(STAMP)
	$(VENV)/bin/jupytext --quiet --to ipynb notebooks/*.py

docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -d site

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
	rm -f lidarjax/raytrace/_lidarjax_native*.so lidarjax/raytrace/_lidarjax_native.json

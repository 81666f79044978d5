# Two entry points: `make demo` and `make test`. Both create .venv when missing and
# (re)install the package into it whenever pyproject.toml changes.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
DEMO_OUT ?= out/demo
PYTEST_ARGS ?=
# Test processes (pytest-xdist, one module per process so module fixtures are built
# once): 2 keeps both cores of the reference machine busy; PYTEST_WORKERS=0 runs all
# in this process. --no-loadscope-reorder hands the modules out in the collection's
# order (tests/conftest.py: the longest first) instead of by their count of tests.
PYTEST_WORKERS ?= 2

.PHONY: demo test lint bench clean browser

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/evhsi demo --out $(DEMO_OUT)

test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q $(if $(filter-out 0,$(PYTEST_WORKERS)),-n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder) $(PYTEST_ARGS)

lint: $(STAMP)
	$(PY) -m ruff check .

bench: $(STAMP)
	$(PY) -m pytest -q -m slow $(PYTEST_ARGS)

# The browser test of `evhsi view` (tests/video/test_viewer.py) needs Chromium and its
# WebDriver; it skips with a reason when they are absent. Debian/Ubuntu, as root:
browser:
	apt-get install -y chromium chromium-driver

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache

# The two set-up commands of the README: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: demo test test-long install install-test clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

install: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .

# MAVProxy (tests/system/test_mavproxy.py routes through it) without its GUI dependencies (vtk,
# opencv, wxPython: hundreds of MB a headless router does not use); its light ones are in [test].
MAVPROXY := MAVProxy==1.8.75

# The suite on every core, each test file on one worker (its module fixtures run once), without
# the tests marked long (a claim's further seeds, the longest drives: tests/conftest.py), which
# `make test-long` runs. `make test PYTEST_ARGS=` runs both tiers, serially.
PARALLEL := -n auto --dist loadfile
PYTEST_ARGS ?= $(PARALLEL) -m "not long"

install-test: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[test]'
	$(BIN)/python -m pip install --quiet --no-deps '$(MAVPROXY)'

demo: install
	$(BIN)/guard demo

test: install-test
	$(BIN)/python -m pytest $(PYTEST_ARGS)

test-long: install-test
	$(BIN)/python -m pytest $(PARALLEL) -m long

clean:
	rm -rf $(VENV) build *.egg-info

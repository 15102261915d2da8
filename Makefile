# Two commands do all the set-up on a fresh machine:
#   make run    the gateway on its embedded default (simulated flight, every backend, loopback)
#   make test   the test suite
# Both create .venv and install the project into it on first use.

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
ARGS ?=
PYTEST_ARGS ?=

.PHONY: run test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[test]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/aurora-gateway run $(ARGS)

test: $(STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/python tools/bench/bench_decode.py
	$(BIN)/python tools/bench/bench_fanout.py
	$(BIN)/python tools/bench/bench_mavlink_router.py
	$(BIN)/python tools/bench/bench_zenoh.py

clean:
	rm -rf $(VENV) build *.egg-info

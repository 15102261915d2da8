# Two commands do all the set-up on a fresh machine:
#   make run    the gateway on its embedded default (simulated flight, every backend, loopback)
#   make test   the test suite
# Each has an environment of its own, created with the project installed editable on first use:
#   .venv-run   `make run`: the runtime install, the project with its `all` extra (every
#               optional backend) and nothing else, as a user's `pip install 'aurora-gateway[all]'`
#   .venv       `make test`, `make lint`, `make bench`, `make bytecode`: the same plus the test
#               and lint tools and the field's own programs (fprime-gds, MAVProxy …)
# The test tools stay out of the runtime: fprime-gds pins fastcrc 0.3 (a copy per frame in the
# router) and the many distributions slow the entry-point scans at start-up.
# Both compile the project's bytecode (cheap when it is up to date): the install is editable,
# and with PYTHONDONTWRITEBYTECODE=1 in the environment Python would otherwise compile every
# module, the generated MAVLink dialect included, in memory on every start.  compileall writes
# the .pyc files whatever that variable says; imports read them whatever it says.

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
RUN_VENV ?= .venv-run
RUN_STAMP := $(RUN_VENV)/.installed-stamp
ARGS ?=
PYTEST_ARGS ?=
# The suite is mostly waiting on sockets, ptys and subprocesses: four workers on two cores.
# Whole files per worker (loadfile): a module-scoped fixture (test_cli's batch of short
# runs, the plot and export recordings) then runs once, as in a serial run, not once per
# worker that happens to get one of its tests.
PYTEST_WORKERS ?= 4

PACKAGES := gateway backends dialects
# The compiled fast paths (pyproject's ext-modules): the editable install builds them in place
# (next to their packages' modules); an edit to one rebuilds them.
SPEEDUPS := backends/mavlink/_route_speedups.c gateway/io/_mmsg_speedups.c

.PHONY: run test lint bench clean bytecode wheel-check

$(RUN_STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(RUN_VENV)
	$(RUN_VENV)/bin/python -m pip install --quiet --disable-pip-version-check -e '.[all]'
	touch $(RUN_STAMP)

$(STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[test]'
	# Stock MAVProxy, the real ground station of tests/test_mavlink_mavproxy.py.  Without its
	# dependencies: those are for its GUI and map modules (vtk, OpenCV, matplotlib: ~240 MB),
	# unused by --daemon --non-interactive; pymavlink and pyserial come with the project.
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps \
		mavproxy==1.8.75 defusedxml==0.7.1 pynmeagps==1.1.8
	touch $(STAMP)

$(VENV)/.speedups-stamp: $(STAMP) $(SPEEDUPS)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
	touch $@

$(RUN_VENV)/.speedups-stamp: $(RUN_STAMP) $(SPEEDUPS)
	$(RUN_VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
	touch $@

# Bytecode of what changed since the last compile (an edit, a git pull).
bytecode: $(STAMP) $(VENV)/.speedups-stamp
	$(BIN)/python -m compileall -q $(PACKAGES)

run: $(RUN_STAMP) $(RUN_VENV)/.speedups-stamp
	$(RUN_VENV)/bin/python -m compileall -q $(PACKAGES)
	$(RUN_VENV)/bin/aurora-gateway run $(ARGS)

test: bytecode
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

bench: bytecode
	$(BIN)/python tools/bench/bench_decode.py
	$(BIN)/python tools/bench/bench_fanout.py
	$(BIN)/python tools/bench/bench_handover.py
	$(BIN)/python tools/bench/bench_mavlink_router.py
	$(BIN)/python tools/bench/bench_zenoh.py
	$(BIN)/python tools/bench/bench_uavtalk.py
	$(BIN)/python tools/bench/bench_fprime.py
	$(BIN)/python tools/bench/bench_xbee.py
	$(BIN)/python tools/bench/bench_threads.py

# The wheel as users install it, outside the checkout (tools/check_wheel.py; .ci/run runs it).
wheel-check:
	$(PYTHON) tools/check_wheel.py

clean:
	rm -rf $(VENV) $(RUN_VENV) build *.egg-info
	find $(PACKAGES) tests tools -name __pycache__ -type d -prune -exec rm -rf {} +

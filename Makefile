# uav_serial_drivers: `make demo` and `make test` work on a fresh machine (they build first).
SHELL := /bin/bash
ENV := source tools/env.sh
PYTEST_ARGS ?=
# Tests run side by side in pytest-xdist workers, each with its own ROS domain: most of a
# test's time is waiting on a device's timing, not CPU, so six workers fit two cores.
TEST_WORKERS ?= 6
# Compiled modules (and pytest's rewritten test modules) are kept between runs, outside the
# tree, even where the environment says not to write them: every worker and node process would
# compile them again (about 4 s of CPU per worker). A cold cache is filled once, before the
# workers start (test/conftest.py).
PYCACHE := export PYTHONDONTWRITEBYTECODE= \
	PYTHONPYCACHEPREFIX=$${XDG_CACHE_HOME:-$$HOME/.cache}/uav_serial_drivers/pycache

.PHONY: all build test test-core demo bench lint clean distclean

all: build

build:
	@$(PYCACHE) && flock .build.lock bash tools/bootstrap.sh

test: build
	@$(ENV) && $(PYCACHE) && python -m pytest test -p no:cacheprovider -n $(TEST_WORKERS) --dist loadgroup \
		--no-loadscope-reorder $(PYTEST_ARGS)

test-core: build
	@$(ENV) && $(PYCACHE) && python -m pytest test -p no:cacheprovider -m core $(PYTEST_ARGS)

lint: build
	@$(ENV) && python -m pytest test/test_lint.py -p no:cacheprovider $(PYTEST_ARGS)

demo: build
	@$(ENV) && $(PYCACHE) && python tools/demo.py

bench: build
	@$(ENV) && python bench/run_all.py

clean:
	rm -rf build install log .build.lock

distclean: clean
	rm -rf "$$(readlink -f .venv)" .venv

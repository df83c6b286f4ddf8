# uav_serial_drivers: `make demo` and `make test` work on a fresh machine (they build first).
SHELL := /bin/bash
ENV := source tools/env.sh
PYTEST_ARGS ?=
# Test files run side by side in pytest-xdist workers, each with its own ROS domain: most of a
# test's time is waiting on a device's timing, not CPU, so four workers fit two cores.
TEST_WORKERS ?= 4

.PHONY: all build test test-core demo bench lint clean distclean

all: build

build:
	@flock .build.lock bash tools/bootstrap.sh

test: build
	@$(ENV) && python -m pytest test -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile \
		--no-loadscope-reorder $(PYTEST_ARGS)

test-core: build
	@$(ENV) && python -m pytest test -p no:cacheprovider -m core $(PYTEST_ARGS)

lint: build
	@$(ENV) && python -m pytest test/test_lint.py -p no:cacheprovider $(PYTEST_ARGS)

demo: build
	@$(ENV) && python tools/demo.py

bench: build
	@$(ENV) && python bench/run_all.py

clean:
	rm -rf build install log .build.lock

distclean: clean
	rm -rf "$$(readlink -f .venv)" .venv

# perfros-bag: every target sets itself up (venv, Debian packages) on a fresh machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# Debian packages the tests and pipelines use: ROS 1 (roscore, rospy, rosbag), real C++
# nodes for `sweep` (image_publisher, opencv_apps: nodelet loaders, which find their plugins
# only with the packages holding nodelet's and their package.xml / nodelet_plugins.xml) and
# a headless browser for the report check; iproute2 (ip, tc) for links as network namespaces;
# topic_tools (throttle, for fixtures/throttle; libtopic-tools-dev holds its package.xml).
DEBS ?= ros-core python3-rospy python3-rosbag ros-image-publisher ros-opencv-apps python3-opencv-apps \
	libnodeletlib-dev libnodelet-dev libnodeletlib-tools libopencv-apps2d libopencv-apps-dev \
	libimage-publisher-dev topic-tools libtopic-tools-dev chromium iproute2
PYTEST_ARGS ?=
OUT ?= out

.PHONY: help setup setup-debs test test-slow lint bench demo clean sanitize
help:
	@echo "make demo   - run the pipeline on the bundled fixtures (sets everything up)"
	@echo "make test   - run the test suite (sets everything up; ~10 min on 2 cores)"
	@echo "make test-slow - the longest real-node end-to-end tests (marked slow)"
	@echo "make lint   - ruff + mypy"
	@echo "make bench  - benchmarks (results: docs/benchmarks.md)"
	@echo "make sanitize - the C sqlite page decoder under ASan/UBSan with a long fuzz"
	@echo "make paper  - the paper's Table II instances with every solver"
	@echo "make casestudy - the case study on real ROS 1 nodes (long)"
	@echo "make casestudy-real - the case study on real C++ nodes, CPU and links emulated (long)"

setup: $(STAMP)

$(STAMP): pyproject.toml perfros_bag/ingest/_sqlitecells.c
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	@touch $@

# Installs the Debian packages when one is missing (needs root, as on CI); otherwise says what to do.
setup-debs:
	@missing=""; for p in $(DEBS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else echo "warning: Debian packages missing:$$missing (run: sudo apt-get install$$missing); tests that need them will fail" >&2; fi; \
	fi

# Two workers (the machine's 2 cores): the tests that run real ROS nodes, cgroups or network
# namespaces share one of them, one at a time (tests/conftest.py); the longest real-node runs
# (marked slow) are left to `make test-slow`.
TEST_WORKERS ?= 2
test: setup setup-debs
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup -m "not slow" $(PYTEST_ARGS)

test-slow: setup setup-debs
	$(PY) -m pytest -q -m slow $(PYTEST_ARGS)

lint: setup
	$(BIN)/ruff check perfros_bag tests pipelines
	$(BIN)/mypy perfros_bag pipelines

bench: setup setup-debs
	$(PY) tests/bench/run.py

# After changing perfros_bag/ingest/_sqlitecells.c: rebuild it with AddressSanitizer and
# UBSan in place, run its tests with 6000 damaged files, then put the normal build back.
EXT_SO = $(shell $(PY) -c 'import sysconfig; print("perfros_bag/ingest/_sqlitecells" + sysconfig.get_config_var("EXT_SUFFIX"))' 2>/dev/null)
sanitize: setup
	@set -e; cp $(EXT_SO) $(EXT_SO).keep; trap 'mv -f $(EXT_SO).keep $(EXT_SO)' EXIT; \
	gcc -shared -fPIC -O1 -g -fsanitize=address,undefined -fno-omit-frame-pointer \
	  -I"$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["include"])')" \
	  perfros_bag/ingest/_sqlitecells.c -o $(EXT_SO); \
	ASAN_OPTIONS=detect_leaks=0 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 PERFROS_FUZZ_CASES=6000 \
	LD_PRELOAD="$$(gcc -print-file-name=libasan.so) $$(gcc -print-file-name=libubsan.so)" \
	  $(PY) -m pytest -q -p no:cacheprovider tests/test_ingest_sqlitepages.py tests/test_ingest_formats.py \
	  tests/test_ingest_broken.py tests/test_ingest_memory.py

clean:
	rm -rf $(OUT) .pytest_cache .mypy_cache .ruff_cache

# Pipelines (characterise, fit, solve, validate, report, paper, casestudy) and the
# demo's steps live in pipelines/*.mk; each adds its final artefacts to DEMO_OUTPUTS.
DEMO_OUTPUTS :=
include $(sort $(wildcard pipelines/*.mk))

demo: setup $(DEMO_OUTPUTS)
	@echo "demo outputs in $(OUT)/demo/"

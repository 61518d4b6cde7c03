# dibrpp — user entry points.  Set-up is two commands: `make setup` then `make test`.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
# Shared libraries the bpy wheel loads (Debian/Ubuntu package names).
BPY_SYSTEM_LIBS := libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libxext6 libsm6 libice6 libgl1
# Headless browser that the test suite opens the HTML evaluation report in; LLVM 19 for Mitsuba's LLVM
# backend (Table B; Dr.Jit aborts with LLVM 15 and 16).
SYSTEM_PKGS := $(BPY_SYSTEM_LIBS) chromium libllvm19
PYTEST_ARGS ?=

DATASETS := metallic glossy diffuse
DATA ?= data
RUNS ?= runs
# Shading methods trained per dataset (the paper's MC and SG, DIB-R's SH baseline), then the seeds of
# the main model (SG) for the variance study; seed 0 is the main SG run itself.
METHODS ?= sg mc sh
SEEDS ?= 1 2
TRAIN_ARGS ?=

# data-% and train-% are pattern rules, which make does not apply to .PHONY targets.
.PHONY: setup system-libs test train-variants test-fast bench bench-renderer bench-train bench-mitsuba studies study-reflections study-maps data eval train-ablations clean help

help:
	@echo "make setup            create $(VENV) and install dibrpp with Blender (bpy), torch and test tools"
	@echo "make test             run the full test suite (includes Cycles comparisons; what CI runs)"
	@echo "make test-fast        the suite without the tests marked slow (> ~30 s on 2 cores): the edit loop"
	@echo "make data             render the metallic, glossy and diffuse datasets with Cycles into $(DATA)/"
	@echo "make data-glossy-hdri the glossy cars under HDRIs from a folder (HDRIS=DIR; default: Blender's 8 bundled maps)"
	@echo "make train-glossy     train SG, MC and SH on $(DATA)/glossy, then SG with seeds $(SEEDS) (also -metallic, -diffuse)"
	@echo "make train-ablations  glossy runs for Tables D and E (SH shading with SG light; K = 4, 8, 16)"
	@echo "make train-variants   glossy SG ablations of our model: light colour, texture, edge antialiasing (F.1), light (README)"
	@echo "make eval             paper metrics of every run under $(RUNS) on the test split (results/eval/)"
	@echo "make bench            Table A, Table B (vs Mitsuba 3) and the training-iteration benchmark (results/bench/)"
	@echo "make studies          renderer studies, Figures A-E: samples vs roughness, SG fits, ambiguity, joint fits (results/studies/)"
	@echo "make study-reflections  how much of the glossy cars' reflection two views share (1.5 min; results/studies/)"
	@echo "make study-maps      glossy cars under 200 env maps instead of 40: data, three SG runs, cross-evaluation (~45 min)"

setup: system-libs $(VENV)/.installed

system-libs:
	@missing=""; for p in $(SYSTEM_PKGS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages (bpy's libraries, chromium, LLVM 19):$$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] && echo "" || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

$(VENV)/.installed: pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found; bpy needs Python 3.11 (set PYTHON=...)"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# torch first and pinned: pip takes the local CPU wheel instead of a multi-GB CUDA build.
	$(PIP) install -q "torch==2.13.0"
	$(PIP) install -q -e ".[blender,dev,bench]"
	$(PY) -c "import torch, bpy, OpenEXR, trimesh, xatlas, skimage; print('torch', torch.__version__, '| bpy', bpy.app.version_string)"
	# dibrpp's C++ kernels (torch's extension mechanism; ~30 s once, into ~/.cache/torch_extensions)
	$(PY) -m dibrpp build-kernels
	touch $@

test: $(VENV)/.installed
	$(PY) -m pytest -q -n 2 $(PYTEST_ARGS)

# Everything but the tests marked @pytest.mark.slow (Cycles renders, benchmark and study smoke runs).
test-fast: $(VENV)/.installed
	$(PY) -m pytest -q -n 2 -m "not slow" $(PYTEST_ARGS)

data: $(addprefix data-,$(DATASETS))

# The glossy cars under real, captured light: a folder of HDRIs (default: the eight CC0 Poly Haven maps that
# ship with Blender) mixed with procedural maps, each kind split 4:1. Train it with
# `make train-glossy-hdri METHODS=sg SEEDS=`.
HDRIS ?= $(shell $(PY) -c "from datagen.envmap_files import blender_hdris; print(blender_hdris())" 2>/dev/null)
data-glossy-hdri: $(VENV)/.installed
	@test -n "$(HDRIS)" || { echo "error: no HDRI folder; set HDRIS=DIR (a folder of .exr / .hdr maps)"; exit 1; }
	$(PY) -m datagen --dataset glossy --envmaps $(HDRIS) --procedural-envmaps 16 --num-objects 60 --out $(DATA)/glossy-hdri

# Resumable: rerunning skips finished samples and redoes partial ones.
data-%: $(VENV)/.installed
	$(PY) -m datagen --dataset $* --out $(DATA)/$*

train-%: $(VENV)/.installed
	@test -f $(DATA)/$*/manifest.json || { echo "error: no dataset in $(DATA)/$*; run 'make data' (or 'make data-$*') first"; exit 1; }
	@set -e; for m in $(METHODS); do \
	  echo "== $* / $$m / seed 0"; \
	  $(PY) -m pipelines.train --dataset $(DATA)/$* --shading $$m --seed 0 --out $(RUNS)/$*/$$m-seed0 --resume $(TRAIN_ARGS); \
	done; \
	for s in $(SEEDS); do \
	  echo "== $* / sg / seed $$s"; \
	  $(PY) -m pipelines.train --dataset $(DATA)/$* --shading sg --seed $$s --out $(RUNS)/$*/sg-seed$$s --resume $(TRAIN_ARGS); \
	done

bench-renderer: $(VENV)/.installed
	$(PY) -m benchmarks.renderer --out results/bench

# Runs for Tables D and E (glossy): DIB-R's diffuse-only shading with SG light, and K = 4, 8, 16 lobes.
train-ablations: $(VENV)/.installed
	@test -f $(DATA)/glossy/manifest.json || { echo "error: no dataset in $(DATA)/glossy; run 'make data-glossy' first"; exit 1; }
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sh-sg --seed 0 --out $(RUNS)/glossy/sh-sg-seed0 --resume $(TRAIN_ARGS)
	@set -e; for k in 4 8 16; do \
	  $(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --lobes $$k --seed 0 --out $(RUNS)/glossy/sg-k$$k-seed0 --resume $(TRAIN_ARGS); \
	done

# Ablations of our model choices (glossy SG): light of any colour instead of white-balanced, the texture
# decoded from the global code instead of looked up in the input, nvdiffrast-style edge antialiasing
# instead of DIB-R's soft silhouette (the paper's Sec. F.1), light scales exponential in the head's output,
# that with the cross-view renders lit by another object's light under the same env map, and the image
# loss only on renders in the other view of each pair, an L1 between the albedos predicted from an object's
# two views, each albedo pulled down to the darker of the two views, the light head at 10x the learning
# rate (with exponential scales), a curriculum that renders every object with its mean albedo for the first
# 500 iterations; and diagnostics, not models: the mean albedo for the whole run (how well the light learns
# when the albedo cannot hold reflections), the light supervised by the GT env map (on the map, and on the
# rough-metal probe: what the encoder can reach when told the answer) and each object's GT roughness (how
# much of the light's error is the roughness/light-blur ambiguity). Last, the cross-view renders swapped to
# the same object under its other env map (--swap-light; two seeds), with the fast log-scaled light head,
# and on the metallic set.
train-variants: $(VENV)/.installed
	@test -f $(DATA)/glossy/manifest.json || { echo "error: no dataset in $(DATA)/glossy; run 'make data-glossy' first"; exit 1; }
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --light-colour free --out $(RUNS)/glossy/sg-free-light-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --texture global --out $(RUNS)/glossy/sg-global-texture-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --visibility edge_aa --out $(RUNS)/glossy/sg-edge-aa-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --light-scale log --out $(RUNS)/glossy/sg-log-light-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --light-scale log --shared-light --out $(RUNS)/glossy/sg-shared-light-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --cross-view-only --out $(RUNS)/glossy/sg-cross-view-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --w-albedo-consistency 1.0 --out $(RUNS)/glossy/sg-albedo-consistency-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --w-albedo-consistency 0.1 --out $(RUNS)/glossy/sg-albedo-consistency-0.1-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --w-albedo-darker 1.0 --out $(RUNS)/glossy/sg-albedo-darker-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --w-albedo-darker 0.1 --out $(RUNS)/glossy/sg-albedo-darker-0.1-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --light-scale log --light-lr-scale 10 --out $(RUNS)/glossy/sg-log-light-lr10-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --flat-albedo-iterations 500 --out $(RUNS)/glossy/sg-flat-albedo-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --flat-albedo-iterations 1500 --out $(RUNS)/glossy/sg-flat-albedo-1500-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --light-supervision map --out $(RUNS)/glossy/sg-light-supervised-map-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --light-supervision probe --out $(RUNS)/glossy/sg-light-supervised-probe-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --oracle-roughness --out $(RUNS)/glossy/sg-oracle-roughness-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --swap-light --out $(RUNS)/glossy/sg-swap-light-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 1 --swap-light --out $(RUNS)/glossy/sg-swap-light-seed1 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --seed 0 --swap-light --light-scale log --light-lr-scale 10 --out $(RUNS)/glossy/sg-swap-light-log-lr10-seed0 --resume $(TRAIN_ARGS)
	@test -f $(DATA)/metallic/manifest.json || { echo "error: no dataset in $(DATA)/metallic; run 'make data-metallic' first"; exit 1; }
	$(PY) -m pipelines.train --dataset $(DATA)/metallic --shading sg --seed 0 --swap-light --out $(RUNS)/metallic/sg-swap-light-seed0 --resume $(TRAIN_ARGS)

# More env maps, same objects: the glossy set with 200 maps instead of 40 (160 for training; the objects, their
# split and the number of images are the glossy set's), SG trained on it (default, --swap-light, and the
# probe-supervised diagnostic), and the same three 40-map runs evaluated on its test split
# (results/eval-maps200/; `make eval` evaluates the 200-map runs). Resumable at every step; run
# `make train-glossy train-variants` first for the 40-map runs.
study-maps: $(VENV)/.installed
	@for r in sg-seed0 sg-swap-light-seed0 sg-light-supervised-probe-seed0; do test -f $(RUNS)/glossy/$$r/checkpoint.pt || \
	  { echo "error: no run $(RUNS)/glossy/$$r; run 'make train-glossy train-variants' first"; exit 1; }; done
	$(PY) -m datagen --dataset glossy --num-envmaps 200 --out $(DATA)/glossy-maps200
	$(PY) -m pipelines.train --dataset $(DATA)/glossy-maps200 --shading sg --seed 0 --out $(RUNS)/glossy-maps200/sg-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy-maps200 --shading sg --seed 0 --swap-light --out $(RUNS)/glossy-maps200/sg-swap-light-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy-maps200 --shading sg --seed 0 --light-supervision probe --out $(RUNS)/glossy-maps200/sg-light-supervised-probe-seed0 --resume $(TRAIN_ARGS)
	@set -e; for r in sg-seed0 sg-swap-light-seed0 sg-light-supervised-probe-seed0; do \
	  $(PY) -m pipelines.evaluate --runs $(RUNS)/glossy/$$r --dataset $(DATA)/glossy-maps200 --out results/eval-maps200; \
	done

# Paper metrics of every trained run under $(RUNS) on its test split (results/eval/).
eval: $(VENV)/.installed
	$(PY) -m pipelines.evaluate --runs $(RUNS) --out results/eval

# Time per training iteration and its split (needs the glossy dataset: make data-glossy).
bench-train: $(VENV)/.installed
	$(PY) -m benchmarks.train_step --dataset $(DATA)/glossy --out results/bench

# Table B: the same env-map optimisation in dibrpp and Mitsuba 3, wall time and peak memory.
bench-mitsuba: $(VENV)/.installed
	$(PY) -m benchmarks.mitsuba --out results/bench

bench: bench-renderer bench-mitsuba bench-train

# Figures A-E of the supplementary material (Sec. B, C) on this machine.
studies: $(VENV)/.installed
	$(PY) -m studies --out results/studies

# How much of the glossy cars' reflection two views of the camera ring share (README, "Why the light stays weak").
study-reflections: $(VENV)/.installed
	@test -f $(DATA)/glossy/manifest.json || { echo "error: no dataset in $(DATA)/glossy; run 'make data-glossy' first"; exit 1; }
	$(PY) -m studies.reflections --dataset $(DATA)/glossy --out results/studies

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info

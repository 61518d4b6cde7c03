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
.PHONY: models demo light-turns setup system-libs test train-published train-variants train-variant-runs reproduce first-look test-fast bench bench-renderer bench-train bench-mitsuba studies study-reflections study-maps study-resolution study-scale data eval train-ablations clean help

help:
	@echo "make reproduce        every paper table and figure end to end: data, every method and seed, Tables D/E, the published model, evaluation, bench, studies (resumable; ~22-29 h on 2 cores; TRAIN_ARGS='--iterations 1500': a quarter of the training)"
	@echo "make first-look       the glossy set, SG, seed 0, evaluated (32 min on 2 cores)"
	@echo "make demo             the shipped glossy model on the example photo: results/demo/overview.png, report.html (seconds)"
	@echo "make light-turns      where the shipped models place the example sky's sun as it goes round (~30 s; results/light-turns/)"
	@echo "make models           retrain, evaluate and ship the models in models/ (glossy and metallic SG)"
	@echo "make setup            create $(VENV) and install dibrpp with Blender (bpy), torch and test tools"
	@echo "make test             run the full test suite (includes Cycles comparisons; what CI runs)"
	@echo "make test-fast        the suite without the tests marked slow (> ~30 s on 2 cores): the edit loop"
	@echo "make data             render the metallic, glossy and diffuse datasets with Cycles into $(DATA)/"
	@echo "make data-glossy-hdri the glossy cars under HDRIs from a folder (HDRIS=DIR; default: Blender's 8 bundled maps)"
	@echo "make data-metallic-sunny  other metallic cars under skies only: a test set with many suns (~4 min)"
	@echo "make data-glossy-elevations  the glossy set with its views at 12, 22, 32 and 42 degrees of elevation in turn"
	@echo "make train-glossy     train SG, MC and SH on $(DATA)/glossy, then SG with seeds $(SEEDS) (also -metallic, -diffuse)"
	@echo "make train-ablations  glossy runs for Tables D and E (SH shading with SG light; K = 4, 8, 16)"
	@echo "make train-published  DIB-R++ as published: SG and MC on each set of PUBLISHED_SETS (default: all three), SG seeds 1-2 on glossy (Tables 1, C, F)"
	@echo "make train-variants   the named variants (ablations, diagnostics; python -m pipelines.train --list-variants)"
	@echo "make eval             paper metrics of every run under $(RUNS) on the test split (results/eval/)"
	@echo "make bench            Table A, Table B (vs Mitsuba 3) and the training-iteration benchmark (results/bench/)"
	@echo "make studies          renderer studies, Figures A-E: samples vs roughness, SG fits, ambiguity, joint fits (results/studies/)"
	@echo "make study-reflections  how much of the glossy cars' reflection two views share (1.5 min; results/studies/)"
	@echo "make study-maps      glossy cars under 200 env maps instead of 40: data, two SG runs, cross-evaluation (~1.2 h)"
	@echo "make study-scale      the SG model about a 1500-iteration base along resolution, length and data: runs in runs-scale/, curves in results/scale/ (resumable; SCALE_POINTS=res128,cars20,... picks points; all of them ~15 h on 2 cores)"
	@echo "make study-resolution  the metallic sun at 32 x 32 against 64 x 64: data, an SG run, evaluation, diagnosis (~1.3 h)"

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

# The metallic cars under skies only (seed 1: other cars, other maps): a test set for the metallic sun, whose
# default test split holds 10 samples on two sunny maps. A run trained on data/metallic has seen none of it:
# python -m pipelines.evaluate --runs runs/metallic --dataset data/metallic-sunny --split all --out results/eval-metallic-sunny
data-metallic-sunny: $(VENV)/.installed
	$(PY) -m datagen --dataset metallic --outdoor-share 1 --num-objects 30 --num-envmaps 30 --seed 1 --out $(DATA)/metallic-sunny

# The glossy set with its views at 12, 22, 32 and 42 degrees of elevation in turn (the same cars, maps and splits):
# to train on more than one elevation, or to ask how a model reads views from other elevations than its own:
# python -m pipelines.evaluate --runs runs/glossy --dataset data/glossy-elevations --out results/eval-elevations
data-glossy-elevations: $(VENV)/.installed
	$(PY) -m datagen --dataset glossy --elevations 12,22,32,42 --out $(DATA)/glossy-elevations

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

# Runs for Tables D and E (glossy): DIB-R's diffuse-only shading with SG light, and the registry's "paper"
# variants (K = 4, 8, 16 lobes).
train-ablations: $(VENV)/.installed
	@test -f $(DATA)/glossy/manifest.json || { echo "error: no dataset in $(DATA)/glossy; run 'make data-glossy' first"; exit 1; }
	$(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sh-sg --seed 0 --out $(RUNS)/glossy/sh-sg-seed0 --resume $(TRAIN_ARGS)
	@$(MAKE) --no-print-directory train-variant-runs VARIANT_KINDS=paper

# The named variants of pipelines/training/variants.py (ablations of our model's choices and diagnostics that read the GT;
# `python -m pipelines.train --list-variants`), each into runs/<dataset>/sg-<variant>-seed<s>.
VARIANT_KINDS ?= ablation,diagnostic
train-variants: $(VENV)/.installed
	@$(MAKE) --no-print-directory train-variant-runs VARIANT_KINDS=$(VARIANT_KINDS)

train-variant-runs: $(VENV)/.installed
	@set -e; $(PY) -m pipelines.train --variant-runs $(VARIANT_KINDS) | while read dataset variant seed; do \
	  test -f $(DATA)/$$dataset/manifest.json || { echo "error: no dataset in $(DATA)/$$dataset; run 'make data-$$dataset' first"; exit 1; }; \
	  echo "== $$dataset / sg / $$variant / seed $$seed"; \
	  $(PY) -m pipelines.train --dataset $(DATA)/$$dataset --shading sg --variant $$variant --seed $$seed \
	    --out $(RUNS)/$$dataset/sg-$$variant-seed$$seed --resume $(TRAIN_ARGS) < /dev/null; \
	done

# DIB-R++ as published (variant published; docs/deviations.md lists what still differs): each method of
# PUBLISHED_METHODS on each set of PUBLISHED_SETS with seed 0, and, where glossy is one of them, SG on glossy with
# the seeds of SEEDS (Table F), into runs/<dataset>/<method>-published-seed<s>. Every set's data is checked before
# anything trains. Table C alone: `make train-published PUBLISHED_SETS=diffuse`. Resumable.
PUBLISHED_METHODS ?= sg mc
PUBLISHED_SETS ?= $(DATASETS)
train-published: $(VENV)/.installed
	@for d in $(PUBLISHED_SETS); do \
	  test -f $(DATA)/$$d/manifest.json || { echo "error: no dataset in $(DATA)/$$d; run 'make data-$$d' first (or leave $$d out: PUBLISHED_SETS=...)"; exit 1; }; \
	done
	@set -e; for d in $(PUBLISHED_SETS); do \
	  for m in $(PUBLISHED_METHODS); do \
	    echo "== $$d / $$m / published / seed 0"; \
	    $(PY) -m pipelines.train --dataset $(DATA)/$$d --shading $$m --variant published --seed 0 \
	      --out $(RUNS)/$$d/$$m-published-seed0 --resume $(TRAIN_ARGS); \
	  done; \
	done
	@set -e; for s in $(if $(filter glossy,$(PUBLISHED_SETS)),$(SEEDS)); do \
	  echo "== glossy / sg / published / seed $$s"; \
	  $(PY) -m pipelines.train --dataset $(DATA)/glossy --shading sg --variant published --seed $$s \
	    --out $(RUNS)/glossy/sg-published-seed$$s --resume $(TRAIN_ARGS); \
	done

# Every table and figure of the paper end to end: the three sets, every method and seed, Tables D/E, the published
# model, evaluation (Tables 1, C-F, Figures O-Q), then Tables A and B and the training-step split (bench) and
# Figures A-E (studies). Resumable: rerun it after an interruption and it continues where it stopped.
reproduce: data
	@for d in $(DATASETS); do $(MAKE) --no-print-directory train-$$d || exit 1; done
	@$(MAKE) --no-print-directory train-ablations
	@$(MAKE) --no-print-directory train-published
	@$(MAKE) --no-print-directory eval
	@$(MAKE) --no-print-directory bench
	@$(MAKE) --no-print-directory studies

# The models that ship in models/ (what `make demo` and the README's predict command use without training): the
# default SG run on each of MODEL_SETS, trained as above, then written in half precision, evaluated as shipped and
# given a model card (pipelines.export_model). Resumable; its outputs are committed.
MODEL_SETS ?= glossy metallic
models: $(VENV)/.installed
	@set -e; for d in $(MODEL_SETS); do \
	  $(MAKE) --no-print-directory data-$$d; \
	  $(MAKE) --no-print-directory train-$$d METHODS=sg SEEDS=; \
	  $(PY) -m pipelines.export_model --run $(RUNS)/$$d/sg-seed0 --out models/$$d-sg \
	    --retrain "make models MODEL_SETS=$$d"; \
	done

# The shipped glossy model on the example photo (examples/car_photo.exr: Cycles, 15 degrees up, azimuth 30):
# results/demo/overview.png and report.html, in seconds.
demo: $(VENV)/.installed
	$(PY) -m pipelines.predict --checkpoint models/glossy-sg --image examples/car_photo.exr --elevation 15 \
	  --azimuth 30 --true-light examples/sky.exr --out results/demo

# Where the shipped models place a known sun: the example car under the example sky, its sun turned in 8 steps, from
# the example photo's camera and the training's (docs/evaluation.md#a-known-sun-turned).
light-turns: $(VENV)/.installed
	$(PY) -m pipelines.light_turns --runs models/glossy-sg models/metallic-sg --out results/light-turns

# A first look: the glossy set, SG, seed 0, evaluated.
first-look: data-glossy
	@$(MAKE) --no-print-directory train-glossy METHODS=sg SEEDS=
	@$(MAKE) --no-print-directory eval

# More env maps, same objects: the glossy set with 200 maps instead of 40 (160 for training; the objects, their
# split and the number of images are the glossy set's), SG trained on it (default, and the probe-supervised
# diagnostic), and the same two 40-map runs evaluated on its test split (results/eval-maps200/; `make eval`
# evaluates the 200-map runs). Resumable at every step; run `make train-glossy train-variants` first for the
# 40-map runs.
study-maps: $(VENV)/.installed
	@for r in sg-seed0 sg-light-supervised-probe-seed0; do test -f $(RUNS)/glossy/$$r/checkpoint.pt || \
	  { echo "error: no run $(RUNS)/glossy/$$r; run 'make train-glossy train-variants' first"; exit 1; }; done
	$(PY) -m datagen --dataset glossy --num-envmaps 200 --out $(DATA)/glossy-maps200
	$(PY) -m pipelines.train --dataset $(DATA)/glossy-maps200 --shading sg --seed 0 --out $(RUNS)/glossy-maps200/sg-seed0 --resume $(TRAIN_ARGS)
	$(PY) -m pipelines.train --dataset $(DATA)/glossy-maps200 --shading sg --seed 0 --variant light-supervised-probe --out $(RUNS)/glossy-maps200/sg-light-supervised-probe-seed0 --resume $(TRAIN_ARGS)
	@set -e; for r in sg-seed0 sg-light-supervised-probe-seed0; do \
	  $(PY) -m pipelines.evaluate --runs $(RUNS)/glossy/$$r --dataset $(DATA)/glossy-maps200 --out results/eval-maps200; \
	done

# The input's resolution: the metallic set and 157 other metallic cars under skies (the larger sunny set of
# docs/experiments.md entries 24-34) rendered at 32 x 32 as well as 64 x 64, SG trained at 32 x 32, and each
# resolution's run evaluated and diagnosed on its own sunny set (results/eval-res64, results/eval-res32).
# Resumable at every step; run `make train-metallic` first for the 64 x 64 run. ~1.3 h on 2 cores.
SUNNY_LARGE := --dataset metallic --outdoor-share 1 --num-objects 120 --num-envmaps 120 --seed 2
study-resolution: $(VENV)/.installed
	@test -f $(RUNS)/metallic/sg-seed0/checkpoint.pt || \
	  { echo "error: no run $(RUNS)/metallic/sg-seed0; run 'make train-metallic' first"; exit 1; }
	$(PY) -m datagen --dataset metallic --resolution 32 --out $(DATA)/metallic-32
	$(PY) -m datagen $(SUNNY_LARGE) --out $(DATA)/metallic-sunny-large
	$(PY) -m datagen $(SUNNY_LARGE) --resolution 32 --out $(DATA)/metallic-sunny-large-32
	$(PY) -m pipelines.train --dataset $(DATA)/metallic-32 --shading sg --seed 0 --out $(RUNS)/metallic-32/sg-seed0 --resume $(TRAIN_ARGS)
	@set -e; for r in 64 32; do \
	  run=$(RUNS)/metallic/sg-seed0; sunny=$(DATA)/metallic-sunny-large; \
	  if [ $$r = 32 ]; then run=$(RUNS)/metallic-32/sg-seed0; sunny=$(DATA)/metallic-sunny-large-32; fi; \
	  $(PY) -m pipelines.evaluate --runs $$run --dataset $$sunny --split all --out results/eval-res$$r; \
	  $(PY) -m pipelines.diagnose_light --run $$run --dataset $$sunny --split all > results/eval-res$$r/diagnose_light.txt; \
	done

# The default SG model along input resolution (32, 64, 128; 256 on a GPU), training length (750 to 24k iterations)
# and training data (10 to 400 cars, 32 or 160 maps), everything else at the glossy set's base point
# (pipelines/scale_study.py, docs/scale.md): each point's set rendered if missing, the run trained, evaluated on the
# test and train splits, then the curves and light rows (results/scale/). Resumable at every step.
SCALE_POINTS ?=
study-scale: $(VENV)/.installed
	$(PY) -m pipelines.scale_study run --data $(DATA) $(if $(SCALE_POINTS),--points $(SCALE_POINTS)) \
	  $(if $(TRAIN_ARGS),--train-args='$(TRAIN_ARGS)')
	$(PY) -m pipelines.scale_study report --data $(DATA)

# Paper metrics of every trained run under $(RUNS) on its test split (results/eval/).
eval: $(VENV)/.installed
	$(PY) -m pipelines.evaluate --runs $(RUNS) --out results/eval

# Time per training iteration and its split (needs the glossy dataset: make data-glossy).
bench-train: $(VENV)/.installed
	@test -f $(DATA)/glossy/manifest.json || { echo "error: no dataset in $(DATA)/glossy; run 'make data-glossy' first"; exit 1; }
	$(PY) -m benchmarks.train_step --dataset $(DATA)/glossy --out results/bench

# Table B: the same env-map optimisation in dibrpp and Mitsuba 3, wall time and peak memory.
bench-mitsuba: $(VENV)/.installed
	$(PY) -m benchmarks.mitsuba --out results/bench

bench: bench-renderer bench-mitsuba bench-train

# Figures A-E of the supplementary material (Sec. B, C) on this machine.
studies: $(VENV)/.installed
	$(PY) -m studies --out results/studies

# How much of the glossy cars' reflection two views of the camera ring share (docs/studies.md#reflections-shared-by-two-views).
study-reflections: $(VENV)/.installed
	@test -f $(DATA)/glossy/manifest.json || { echo "error: no dataset in $(DATA)/glossy; run 'make data-glossy' first"; exit 1; }
	$(PY) -m studies.reflections --dataset $(DATA)/glossy --out results/studies

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info

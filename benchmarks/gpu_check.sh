#!/usr/bin/env bash
# The GPU path at the paper's size, in one call of about 8 minutes on one CUDA GPU:
#   benchmarks/gpu_check.sh DATASET OUT [TRAIN_SECONDS]
# DATASET: a set rendered at 256 x 256 (python -m datagen --preset paper ...); OUT: where the results go.
#  1. the CUDA tests (the renderer's CPU/CUDA parity, MC replay, one training step on either device);
#  2. Cycles on the GPU: 2 objects at the paper preset (256 x 256, 256 spp) rendered with --cycles-device gpu;
#  3. the paper preset's training step at 256 x 256, batch 16, SG and MC (benchmarks.train_step);
#  4. SG trained with the paper preset for about TRAIN_SECONDS (default 180) of steps at the measured rate, its
#     cosine tail over that length, then evaluated (EVAL_DEVICE, default cpu: on an H200 `--device cuda` had not
#     finished its first batch after ~100 s, its renderers compiling for each batch shape) and one image predicted
#     on the GPU.
# The 200k-iteration recipe's time on this GPU is the step time times 200 000 (printed at the end).
set -euo pipefail
data=${1:?usage: benchmarks/gpu_check.sh DATASET OUT [TRAIN_SECONDS]}
out=${2:?usage: benchmarks/gpu_check.sh DATASET OUT [TRAIN_SECONDS]}
seconds=${3:-180}
py=${PYTHON:-python3}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
$py -c "import torch; print('torch', torch.__version__, '|', torch.cuda.get_device_name(), '|', torch.cuda.device_count(), 'GPU')"

echo "== CUDA tests"
$py -m pytest -q -p no:cacheprovider -o addopts="" tests/dibrpp/test_shading.py tests/dibrpp/test_lights.py \
  tests/dibrpp/test_mc_replay.py tests/pipelines/test_train.py -k "cuda" 2>&1 | tail -5

echo "== Cycles on the GPU: 2 objects, paper preset"
if $py -c "import bpy" 2>/dev/null; then
  $py -m datagen --dataset glossy --preset paper --num-objects 2 --num-envmaps 4 --envs-per-object 1 --views 8 \
    --cycles-device gpu --quiet --no-preview --out "$out/data-gpu" | tail -1
else
  echo "skipped: Blender's bpy does not import with $($py -V 2>&1) here (bpy 5.0 is built for Python 3.11 only)"
fi

echo "== the paper preset's training step (256 x 256, batch 16)"
$py -m benchmarks.train_step --dataset "$data" --preset paper --device cuda --shading sg mc --iterations 20 \
  --warmup 3 --out "$out/bench"

ms=$($py -c "import csv, sys; print([r for r in csv.DictReader(open(sys.argv[1])) if r['shading'] == 'sg'][0]['total'])" \
  "$out/bench/train.csv")
iterations=$($py -c "import sys; print(max(20, int(float(sys.argv[1]) * 1000 / float(sys.argv[2]))))" "$seconds" "$ms")
echo "== SG, paper preset, $iterations iterations (~${seconds} s at $ms ms a step)"
start=$(date +%s)
$py -m pipelines.train --preset paper --dataset "$data" --shading sg --device cuda --iterations "$iterations" \
  --checkpoint-every "$iterations" --log-every 10 --out "$out/run" --no-progress
echo "trained in $(( $(date +%s) - start )) s"

echo "== evaluation (${EVAL_DEVICE:-cpu}) and prediction on the GPU"
start=$(date +%s)
$py -m pipelines.evaluate --runs "$out/run" --dataset "$data" --device "${EVAL_DEVICE:-cpu}" --out "$out/eval"
echo "evaluated in $(( $(date +%s) - start )) s"
image=$(ls "$data"/samples/*/view_00.exr | head -1)
$py -m pipelines.predict --checkpoint "$out/run" --image "$image" --device cuda --out "$out/predict"

$py -c "import sys; ms = float(sys.argv[1]); print(f'the paper recipe, 200k iterations at {ms:.0f} ms: {ms * 200:.0f} s = {ms * 200 / 3600:.1f} h on this GPU')" "$ms"
